"""The C interface around the derived step: ``<name>.h`` and the public functions of ``<name>.c``.

The step itself is printed from the formulas (:mod:`.c_derive`); this module writes what a
controller calls: the state struct (the formulas' state row), ``<name>_init``,
``<name>_step``, ``<name>_phi_hat``, the accessors and ``<name>_error_message``, with the
status codes of :data:`STATUS` (the one table the loader and the docs read).

What lives here: :class:`CLayout`, :func:`header_source`, :func:`source_text` and
:data:`STATUS`. What it may import: :mod:`thetahat.estimation.status`, the derived step of
:mod:`.c_derive` and the text rules of :mod:`.c_text`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from string import Template

from ..estimation.status import MESSAGES, Status
from .c_derive import DerivedStep
from .c_text import string_literal

__all__ = ["STATUS", "CLayout", "header_source", "source_text"]

#: Status codes of the generated functions (``<NAME>_OK``, ``<NAME>_ERR_…``), by name, with
#: their message: derived from :class:`~thetahat.estimation.status.Status` (the codes the
#: formulas return, so the step's status passes through unchanged).
STATUS = {s.name.lower(): (int(s), MESSAGES[s]) for s in Status}


@dataclass(frozen=True)
class CLayout:
    """What the interface needs to know of the observer.

    Attributes
    ----------
    prefix : str
    real : {"double", "float"}
    dims : tuple of int
        (n, m, r, k, p).
    second, skip, foh : bool
        A second observer; ``nan_policy="skip"``; first-order hold.
    """

    prefix: str
    real: str
    dims: tuple[int, int, int, int, int]
    second: bool
    skip: bool
    foh: bool

    @property
    def size(self) -> int:
        """Length of the state row."""
        n, _, _, k, p = self.dims
        return n + k + p + (n if self.second else 0)


def _enum(PU: str) -> str:
    rows = [f"    {PU}_{'OK' if key == 'ok' else 'ERR_' + key.upper()} = {code}"
            for key, (code, _) in STATUS.items()]
    return ",\n".join(rows)


def header_source(lay: CLayout, banner: str) -> str:
    """``<name>.h``: types, sizes, status codes, the state and the prototypes.

    Parameters
    ----------
    lay : CLayout
    banner : str
        The comment at the top.

    Returns
    -------
    str

    Examples
    --------
    >>> text = header_source(CLayout("obs", "double", (2, 1, 1, 1, 1), False, False, False), "")
    >>> 'extern "C"' in text and "int obs_step(obs_state *s" in text
    True
    """
    P, PU = lay.prefix, lay.prefix.upper()
    n, m, r, k, p = lay.dims
    nxt = (f",\n{' ' * (len(P) + 10)}const {P}_real_t u_next[], const {P}_real_t y_next[]"
           if lay.foh else "")
    step_doc = ("/* Advance by dt from the samples (u, y) to the next ones (u_next, y_next),\n"
                " * interpolated linearly (first-order hold; u may be NULL when NU = 0). */"
                if lay.foh else
                "/* Advance by dt holding the samples u[NU] (may be NULL when NU = 0) and "
                "y[NY]. */")
    second = (f"const {P}_real_t *{P}_x_hat_refined(const {P}_state *s);\n"
              if lay.second else "")
    second_row = ", x_hat_refined" if lay.second else ""
    return banner + f"""#ifndef {PU}_H
#define {PU}_H

#ifdef __cplusplus
extern "C" {{
#endif

typedef {lay.real} {P}_real_t;

#define {PU}_NX {n} /* states x */
#define {PU}_NU {m} /* inputs u */
#define {PU}_NY {r} /* outputs y */
#define {PU}_NK {k} /* perturbation phi */
#define {PU}_NP {p} /* parameters theta */
#define {PU}_NS {lay.size} /* the state row: x_hat, z, theta_hat{second_row} */

/* Status codes of {P}_init, {P}_step and {P}_phi_hat ({P}_error_message explains them). On an
 * error the state is left unchanged. */
enum {{
{_enum(PU)}
}};

/* The observer state, owned by the caller: the row col(x_hat, z, theta_hat[, x_hat_2]) of
 * the formulas (x_hat of (3a), z of (3b) with phi_hat = g + z (3c), theta_hat of (8) in
 * Theta, x_hat_2 of the second observer of Sec. VI). Read it with the accessors. */
typedef struct {P}_state {{
    {P}_real_t s[{PU}_NS];
}} {P}_state;

/* Start at theta_hat0 (in Theta) and x_hat0; NULL for the generated defaults. */
int {P}_init({P}_state *s, const {P}_real_t theta_hat0[], const {P}_real_t x_hat0[]);
/* x_hat <- x_hat + C^+ (y - C x_hat) with the first output sample y, after {P}_init: the state
 * nearest x_hat0 that fits y (thetahat.estimation.observer.initial_state); a y with a NaN keeps x_hat0. */
int {P}_start_from_y({P}_state *s, const {P}_real_t y[]);
{step_doc}
int {P}_step({P}_state *s, const {P}_real_t u[], const {P}_real_t y[]{nxt});
/* phi_hat = g(v, x_hat, theta_hat) + z (3c) at the current samples. */
int {P}_phi_hat(const {P}_state *s, const {P}_real_t u[], const {P}_real_t y[],
{' ' * (len(P) + 12)}{P}_real_t phi_hat[]);
const {P}_real_t *{P}_x_hat(const {P}_state *s);
const {P}_real_t *{P}_theta_hat(const {P}_state *s);
{second}const char *{P}_error_message(int status);

#ifdef __cplusplus
}}
#endif

#endif /* {PU}_H */
"""


_API = r"""
/* ---- the interface (thetahat.codegen.c_api) */

/* u finite and y not inf; *present: y holds no NaN. */
static int read_sample(const real_t u[], const real_t y[], int *present)
{
    int i;
    *present = 1;
    for (i = 0; i < NU; ++i) {
        if (!isfinite(u[i])) {
            return ${PU}_ERR_INPUT;
        }
    }
    for (i = 0; i < NY; ++i) {
        if (isinf(y[i])) {
            return ${PU}_ERR_INPUT;
        }
        if (isnan(y[i])) {
            *present = 0;
        }
    }
    return ${PU}_OK;
}

/* The sample under the NaN policy: *correct is 0 for a missing y (nan_policy "skip"). */
static int samples(const real_t u[], const real_t y[], int *correct)
{
    int status = read_sample(u, y, correct);
    if (status == ${PU}_OK && !*correct && !${SKIP}) {
        return ${PU}_ERR_MISSING;
    }
    return status;
}

int ${P}_init(${P}_state *s, const real_t theta_hat0[], const real_t x_hat0[])
{
    const real_t *th = theta_hat0 != 0 ? theta_hat0 : THETA_HAT0;
    const real_t *x0 = x_hat0 != 0 ? x_hat0 : X_HAT0;
    real_t big = 1, dist2 = 0, d;
    int i;
    for (i = 0; i < NP; ++i) {
        if (!isfinite(th[i])) {
            return ${PU}_ERR_INIT;
        }
        big = FABS(th[i]) > big ? FABS(th[i]) : big;
        d = th[i] < THETA_LOWER[i] ? THETA_LOWER[i] - th[i]
            : (th[i] > THETA_UPPER[i] ? th[i] - THETA_UPPER[i] : 0);
        dist2 += d * d;
    }
    for (i = 0; i < NX; ++i) {
        if (!isfinite(x0[i])) {
            return ${PU}_ERR_INIT;
        }
    }
    if (!(SQRT(dist2) <= INIT_RTOL * big)) {
        return ${PU}_ERR_INIT;
    }
    for (i = 0; i < NS; ++i) {
        s->s[i] = 0;
    }
    for (i = 0; i < NX; ++i) {
        s->s[i] = x0[i];
${INIT_SECOND}    }
    for (i = 0; i < NP; ++i) {
        s->s[NX + NK + i] = th[i] < THETA_LOWER[i] ? THETA_LOWER[i]
                            : (th[i] > THETA_UPPER[i] ? THETA_UPPER[i] : th[i]);
    }
    return ${PU}_OK;
}

int ${P}_start_from_y(${P}_state *s, const real_t y[])
{
    real_t e[NY], d;
    int i, j;
    for (j = 0; j < NY; ++j) {
        if (!isfinite(y[j])) {
            return ${PU}_OK;
        }
    }
    for (j = 0; j < NY; ++j) {
        e[j] = y[j];
        for (i = 0; i < NX; ++i) {
            e[j] -= OUT_C[j * NX + i] * s->s[i];
        }
    }
    for (i = 0; i < NX; ++i) {
        d = 0;
        for (j = 0; j < NY; ++j) {
            d += OUT_CPINV[i * NY + j] * e[j];
        }
        s->s[i] += d;
${START_SECOND}    }
    return ${PU}_OK;
}

int ${P}_step(${P}_state *state, const real_t u[], const real_t y[]${NEXT_PARAMS})
{
    real_t *s = state->s;
    real_t next[NS]${STEP_DECL};
${STEP_BUFFERS}    int correct, status, i${NEXT_INT};
    status = samples(u, y, &correct);
    if (status != ${PU}_OK) {
        return status;
    }
${NEXT_COPY}${STEP_COPY}${STEP_CALLS}    for (i = 0; i < NS; ++i) {
        s[i] = next[i];
    }
    return ${PU}_OK;
}

int ${P}_phi_hat(const ${P}_state *state, const real_t u[], const real_t y[], real_t phi_hat[])
{
    real_t s[NS]${PHI_DECL};
${PHI_BUFFERS}    int correct, status, i;
    status = samples(u, y, &correct);
    if (status != ${PU}_OK) {
        return status;
    }
    for (i = 0; i < NS; ++i) {
        s[i] = state->s[i];
    }
${PHI_COPY}${PHI_CALLS}    return ${PU}_OK;
}

const real_t *${P}_x_hat(const ${P}_state *s)
{
    return s->s;
}

const real_t *${P}_theta_hat(const ${P}_state *s)
{
    return s->s + NX + NK;
}
${ACCESS_SECOND}
const char *${P}_error_message(int status)
{
    switch (status) {
${MESSAGES}    default:
        return "unknown status";
    }
}
"""

_NEXT_CHECK = r"""    status = read_sample(u_next, y_next, &next_present);
    if (status != ${PU}_OK) {
        return status;
    }
"""


def _copies(calls: str, foh: bool) -> tuple[str, str]:
    """Declarations and copies of the sample buffers the calls use (u0, y0[, u1, y1])."""
    names = set(re.findall(r"[A-Za-z_]\w*", calls))
    decl, copy = "", ""
    rows = [("u0", "NUB", "NU", "u[i]"), ("y0", "NY", "NY", "y[i]")]
    if foh:
        rows += [("u1", "NUB", "NU", "u_next[i]"),
                 ("y1", "NY", "NY", "next_present ? y_next[i] : y[i]")]
    for name, size, count, value in rows:
        if name not in names:
            continue
        decl += f", {name}[{size}]"
        copy += (f"    for (i = 0; i < {count}; ++i) {{\n        {name}[i] = {value};\n    }}\n")
    return decl, copy


def source_text(lay: CLayout, banner: str, step: DerivedStep) -> str:
    """``<name>.c``: the constants, the derived step and the interface.

    Parameters
    ----------
    lay : CLayout
    banner : str
    step : DerivedStep

    Returns
    -------
    str
    """
    P, PU = lay.prefix, lay.prefix.upper()
    suffix = "" if lay.real == "double" else "f"
    messages = "".join(
        f"    case {PU}_{'OK' if key == 'ok' else 'ERR_' + key.upper()}:\n"
        f"        return {string_literal(text)};\n" for key, (_, text) in STATUS.items())
    access = (f"\nconst real_t *{P}_x_hat_refined(const {P}_state *s)\n{{\n"
              "    return s->s + NX + NK + NP;\n}\n" if lay.second else "")
    step_decl, step_copy = _copies(step.step_calls, lay.foh)
    phi_decl, phi_copy = _copies(step.phi_calls, False)
    api = Template(_API).safe_substitute(
        SKIP="1" if lay.skip else "0",
        INIT_SECOND="        s->s[NX + NK + NP + i] = x0[i];\n" if lay.second else "",
        START_SECOND="        s->s[NX + NK + NP + i] = s->s[i];\n" if lay.second else "",
        NEXT_PARAMS=(",\n" + " " * (len(P) + 10) + "const real_t u_next[], const real_t "
                     "y_next[]") if lay.foh else "",
        STEP_DECL=step_decl, STEP_COPY=step_copy, PHI_DECL=phi_decl, PHI_COPY=phi_copy,
        NEXT_COPY=_NEXT_CHECK if lay.foh else "", NEXT_INT=", next_present = 0" if lay.foh else "",
        STEP_BUFFERS=step.step_buffers, STEP_CALLS=step.step_calls,
        PHI_BUFFERS=step.phi_buffers, PHI_CALLS=step.phi_calls,
        ACCESS_SECOND=access, MESSAGES=messages)
    api = Template(api).safe_substitute(P=P, PU=PU)
    return banner + f"""#include "{P}.h"

#include <math.h>

#if defined(__FAST_MATH__) || (defined(__FINITE_MATH_ONLY__) && __FINITE_MATH_ONLY__)
#error "compile without -ffast-math or -ffinite-math-only: the NaN policy needs isfinite()"
#endif

typedef {P}_real_t real_t;

#define NX {PU}_NX
#define NU {PU}_NU
#define NY {PU}_NY
#define NK {PU}_NK
#define NP {PU}_NP
#define NS {PU}_NS
#define NUB (NU > 0 ? NU : 1)
#define SQRT sqrt{suffix}
#define FABS fabs{suffix}

/* ---- constants: matrices row-major, the discretisation for the fixed dt */
{step.constants}
/* ---- g, its Jacobians and theta*: SymPy's C99 printer after sympy.cse;
 * ---- the step: thetahat.estimation.observer.formulas and law_formulas, printed by
 *      thetahat.codegen.c_printer (specialised for this observer) */
{step.functions}{api}"""
