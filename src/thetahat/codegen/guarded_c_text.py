"""The fixed text around the printed guard: ``<name>.h``, the step, the CSV harness, the Makefile.

:func:`~thetahat.codegen.guarded_c.generate_guarded_c` prints the guard's loop over the EKF's
kernels; this module puts it in a translation unit with the state struct, ``<name>_init`` and
``<name>_step`` — what :meth:`GuardedEstimator.step
<thetahat.estimation.statistical.guarded.GuardedEstimator.step>` does around the loop: the
input check, stage 1's θ̂_G and x̂ read before stage 1 advances, the loop over this sample
(with the previous one's input for the prediction), then stage 1's step — and writes the
harness ``<name>_main.c`` and a ``Makefile`` that builds both translation units.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .ekf_c_text import csv_main, smooth_state
from .harness import C_FLAGS

__all__ = ["guarded_header", "guarded_main", "guarded_makefile", "guarded_source"]


def guarded_header(name: str, banner: str, sizes: dict[str, Any]) -> str:
    """``<name>.h``: sizes, status codes, the state and the two functions.

    Parameters
    ----------
    name : str
        The C prefix (stage 1's is ``<name>_stage1``).
    banner : str
        The files' opening comment.
    sizes : dict
        n, m, r, p.

    Returns
    -------
    str

    Examples
    --------
    >>> "int g_step(g_state *st" in guarded_header("g", "", {"n": 2, "m": 1, "r": 1, "p": 1})
    True
    """
    P, PU = name, name.upper()
    n, m, r, p = sizes["n"], sizes["m"], sizes["r"], sizes["p"]
    N = n + p
    return banner + f"""#ifndef {PU}_H
#define {PU}_H

#include "{P}_stage1.h"

#ifdef __cplusplus
extern "C" {{
#endif

typedef double {P}_real_t;

enum {{ {PU}_NX = {n}, {PU}_NU = {m}, {PU}_NY = {r}, {PU}_NTHETA = {p}, {PU}_NS = {N} }};

/* What {P}_step returns. */
enum {P}_status {{
    {PU}_OK = 0,                /* the sample was processed */
    {PU}_NONFINITE_INPUT = 1,   /* NaN or inf in u, or inf in y: refused, state unchanged */
    {PU}_STAGE1 = 2,            /* stage 1 refused the sample (a NaN it may not skip):
                                   state unchanged ({P}_state.stage1_status has its code) */
    {PU}_BAD_FIT = 3            /* {P}_apply_fit: theta outside Theta or not finite, a
                                   covariance or sigma not finite, sigma <= 0: not applied */
}};

/* The estimator's state. stage1: the paper's observer; s = col(x_hat_2, theta_hat_2) and P:
   stage 2 (the joint EKF, row-major P), R its measurement noise covariance; cfg the guard's
   constants and its latest fit; pst, gst: stage 1's progress and the guard's own state;
   u_prev: the last input stage 2 read (u_hist, u_sums: the history of the hold "smooth"'s
   correction). After each step: theta_hat the guarded estimate (in Theta),
   x_hat stage 2's x_hat, theta_stage1 and theta_stage2 the two stages' estimates, band the
   guard's delta, clipped / reset whether the guard clipped stage 2 / reset it from stage 1.
   stage1_lost_at: 0 while stage 1 runs; when its step fails (it diverged: stage1_status has
   the code) the sample from which it is lost. From there, as the Python stream: the guard's
   band is Theta's full width, stage 2 goes on alone (reset, when not finite, to the start
   values), theta_stage1 is NaN; the paper's guarantee is gone. */
typedef struct {P}_state {{
    {P}_stage1_state stage1;
    {P}_real_t s[{N}];
    {P}_real_t P[{N * N}];
    {P}_real_t R[{r * r}];
    {P}_real_t cfg[{4 + 3 * p}];
    {P}_real_t pst[{6 * p}];
    {P}_real_t gst[3];
    {P}_real_t u_prev[{max(m, 1)}];
{smooth_state(P, sizes)[0]}    {P}_real_t theta_hat[{p}];
    {P}_real_t x_hat[{n}];
    {P}_real_t theta_stage1[{p}];
    {P}_real_t theta_stage2[{p}];
    {P}_real_t band[{p}];
    int clipped;
    int reset;
    int stage1_status;
    long stage1_lost_at;
    long k;
}} {P}_state;

/* Both stages at their start values (theta_hat0, x_hat0 printed into the C). */
int {P}_init({P}_state *st);
/* One sample: the guard on stage 1's estimate at this sample and stage 2 (predicted from the
   previous sample, updated with y unless y has a NaN), then stage 1 advances by dt. */
int {P}_step({P}_state *st, const {P}_real_t u[], const {P}_real_t y[]);
/* Re-anchor stage 2 on a fit supplied by a host or a lower-priority task (thetahat's MAP fit of
   the data so far, or of a window): theta_hat_2 <- theta (in Theta), the theta block of P <-
   cov_theta (p x p, row-major; cross terms zeroed), R <- diag(sigma^2), and the guard's band
   keeps |theta_G - theta| + kappa * sqrt(diag cov_theta) open, as the Python stream applies a
   consistent fit at its next step. Call it between two steps. */
int {P}_apply_fit({P}_state *st, const {P}_real_t theta[], const {P}_real_t cov_theta[],
                 const {P}_real_t sigma[]);

#ifdef __cplusplus
}}
#endif

#endif /* {PU}_H */
"""


def guarded_source(name: str, banner: str, consts: Sequence[str], rhs: str, kernels: str, *,
                   loop: str, init: str, fit: str, samples: str,
                   sizes: dict[str, Any]) -> str:
    """``<name>.c``: the data, f and its Jacobians, the printed loop, init and step.

    Parameters
    ----------
    name, banner : str
    consts : sequence of str
        ``static const`` arrays (C_OUT, R_NOISE, …, S0, P0, CFG).
    rhs : str
        ``rhs_jac`` printed by SymPy.
    kernels : str
        The printed kernels (callees first).
    loop, init, fit : str
        The calls of the printed ``guarded_loop`` (over row ``k0`` of its two-row arrays),
        ``progress_reset`` and ``apply_fit`` (of ``TF``, ``CF``, ``SF``).
    samples : str
        The statements that set ``Ut`` (stage 2's samples) from ``u`` and advance ``w``'s
        history (:func:`~thetahat.codegen.ekf_c.input_samples`).
    sizes : dict
        n, m, r, p, the hold and ``x_stage1``, the accessor of stage 1's x̂
        (``x_hat_refined`` with the second observer of Sec. VI, else ``x_hat``).

    Returns
    -------
    str
    """
    P, PU = name, name.upper()
    n, m, r, p = sizes["n"], sizes["m"], sizes["r"], sizes["p"]
    N = n + p
    return banner + f"""#include <math.h>
#include "{P}.h"

typedef {P}_real_t real_t;

#define K_HOLD 1073741825L

{chr(10).join(consts)}

{rhs}

{kernels}
int {P}_init({P}_state *st)
{{
    int i, status = {P}_stage1_init(&st->stage1, 0, 0);
    if (status != 0) return status;
    for (i = 0; i < {N}; ++i) st->s[i] = S0[i];
    for (i = 0; i < {N * N}; ++i) st->P[i] = P0[i];
    for (i = 0; i < {r * r}; ++i) st->R[i] = R_NOISE[i];
    for (i = 0; i < {4 + 3 * p}; ++i) st->cfg[i] = CFG[i];
    for (i = 0; i < {6 * p}; ++i) st->pst[i] = 0.0;
    st->gst[0] = 0.0;
    st->gst[1] = 1.0;
    st->gst[2] = 0.0;
    for (i = 0; i < {max(m, 1)}; ++i) st->u_prev[i] = 0.0;
    {smooth_state(P, sizes)[1]}
    for (i = 0; i < {p}; ++i) {{
        st->theta_hat[i] = S0[{n} + i];
        st->theta_stage1[i] = S0[{n} + i];
        st->theta_stage2[i] = S0[{n} + i];
        st->band[i] = 0.0;
    }}
    for (i = 0; i < {n}; ++i) st->x_hat[i] = S0[i];
    st->clipped = 0;
    st->reset = 0;
    st->stage1_status = 0;
    st->stage1_lost_at = 0;
    st->k = 0;
    return {PU}_OK;
}}

int {P}_step({P}_state *st, const real_t u[], const real_t y[])
{{
    {P}_state work = *st;            /* committed only when the sample is processed */
    {P}_state *w = &work;
    real_t U[{2 * max(m, 1)}], Y[{2 * r}], tt[2], Ut[{max(m, 1)}], Raw[{max(m, 1)}];
    real_t THG[{2 * p}], XG[{2 * n}];
    real_t TH[{2 * p}], TH2[{2 * p}], X2[{2 * n}], SD2[{2 * p}], BAND[{2 * p}], NIS[2];
    real_t CLIP[2], RESET[2];
    const int lost = st->stage1_lost_at > 0;      /* stage 1 lost: the start values */
    const real_t *thg = lost ? S0 + {n} : {P}_stage1_theta_hat(&st->stage1);
    const real_t *xg = lost ? S0 : {P}_stage1_{sizes['x_stage1']}(&st->stage1);
    int i, j, k0 = st->k > 0 ? 1 : 0, status;
    /* the absolute index the guard sees, held at 2^30 + 1 (not a power of two: the dyadic
       blocks stop shifting there) so that an int never overflows on a long run */
    int koff = (int)((st->k < K_HOLD ? st->k : K_HOLD) - k0);
    for (i = 0; i < {m}; ++i)
        if (!isfinite(u[i])) return {PU}_NONFINITE_INPUT;
    for (i = 0; i < {r}; ++i)
        if (isinf(y[i])) return {PU}_NONFINITE_INPUT;
    {samples}
    /* rows 0 (the previous sample, for the prediction) and k0 (this one) of the loop */
    for (j = 0; j < 2; ++j) {{
        for (i = 0; i < {m}; ++i) U[j * {max(m, 1)} + i] = (j < k0) ? st->u_prev[i] : Ut[i];
        for (i = 0; i < {r}; ++i) Y[j * {r} + i] = (j < k0) ? NAN : y[i];
        for (i = 0; i < {p}; ++i) THG[j * {p} + i] = thg[i];
        for (i = 0; i < {n}; ++i) XG[j * {n} + i] = xg[i];
    }}
    tt[0] = 0.0;
    tt[1] = DT;
    if (st->k == 0) {init};
    (void){loop};
    if (!lost) {{
        status = {P}_stage1_step(&w->stage1, u, y);
        if (status == {PU}_STAGE1_ERR_INPUT || status == {PU}_STAGE1_ERR_MISSING) {{
            st->stage1_status = status;
            return {PU}_STAGE1;
        }}
        if (status != 0) {{                          /* diverged: lost from the next sample */
            w->stage1 = st->stage1;
            w->stage1_status = status;
            w->stage1_lost_at = st->k + 1;
            w->cfg[2] = 0.0;                         /* rho_max 0: delta_G = |Theta| */
        }}
    }}
    for (i = 0; i < {p}; ++i) {{
        w->theta_hat[i] = TH[k0 * {p} + i];
        w->theta_stage1[i] = lost ? NAN : thg[i];
        w->theta_stage2[i] = TH2[k0 * {p} + i];
        w->band[i] = BAND[k0 * {p} + i];
    }}
    for (i = 0; i < {n}; ++i) w->x_hat[i] = X2[k0 * {n} + i];
    w->clipped = CLIP[k0] != 0.0;
    w->reset = RESET[k0] != 0.0;
    if (!w->stage1_lost_at) w->stage1_status = 0;
    for (i = 0; i < {m}; ++i) w->u_prev[i] = Ut[i];
    w->k += 1;
    *st = work;
    (void)SD2; (void)NIS; (void)U; (void)Y; (void)Ut; (void)Raw;
    return {PU}_OK;
}}

int {P}_apply_fit({P}_state *st, const real_t theta[], const real_t cov_theta[],
                 const real_t sigma[])
{{
    real_t TF[{p}], CF[{p * p}], SF[{r}];
    {P}_state *w = st;
    int i;
    for (i = 0; i < {p}; ++i) {{
        if (!isfinite(theta[i]) || theta[i] < THETA_LO[i] || theta[i] > THETA_HI[i]
                || !isfinite(cov_theta[i * {p} + i]) || cov_theta[i * {p} + i] < 0.0)
            return {PU}_BAD_FIT;
        TF[i] = theta[i];
    }}
    for (i = 0; i < {p * p}; ++i) {{
        if (!isfinite(cov_theta[i])) return {PU}_BAD_FIT;
        CF[i] = cov_theta[i];
    }}
    for (i = 0; i < {r}; ++i) {{
        if (!isfinite(sigma[i]) || !(sigma[i] > 0.0)) return {PU}_BAD_FIT;
        SF[i] = sigma[i];
    }}
    {fit};
    return {PU}_OK;
}}
"""


def guarded_main(name: str, banner: str, sizes: dict[str, Any]) -> str:
    """``<name>_main.c``: ``<name> DATA.csv`` reads rows ``t,u_1…u_m,y_1…y_r`` after a header
    line and writes ``t,x_hat_…,theta_hat_…,theta_stage1_…,theta_stage2_…,band_…`` rows to
    stdout; exit 1 on a bad row or file, 2 on a refused sample (the row named on stderr); a
    stage 1 that stops is said once on stderr, and the rows go on.

    Parameters
    ----------
    name : str
        The C prefix.
    banner : str
        The files' opening comment.
    sizes : dict
        n, m, r, p.

    Returns
    -------
    str

    Examples
    --------
    >>> "g_step(&st, u, y)" in guarded_main("g", "", {"n": 2, "m": 1, "r": 1, "p": 1})
    True
    """
    P, PU = name, name.upper()
    n, m, r, p = sizes["n"], sizes["m"], sizes["r"], sizes["p"]
    head = ",".join(["t", *(f"x_hat_{i + 1}" for i in range(n)),
                     *(f"{w}_{i + 1}" for w in ("theta_hat", "theta_stage1", "theta_stage2",
                                                "band") for i in range(p))])
    prelude = f"""
static void put(const {P}_real_t *v, int n)
{{
    int i;
    for (i = 0; i < n; ++i) printf(",%.17g", v[i]);
}}
"""
    init = (f"if ({P}_init(&st) != {PU}_OK) {{\n"
            '        fprintf(stderr, "%s: stage 1 refused its start values\\n", argv[0]);\n'
            "        fclose(in);\n        return 1;\n    }")
    row = (f"put(st.x_hat, {n});\n        put(st.theta_hat, {p});\n"
           f"        put(st.theta_stage1, {p});\n        put(st.theta_stage2, {p});\n"
           f"        put(st.band, {p});\n"
           "        if (st.stage1_lost_at == st.k)\n"
           '            fprintf(stderr, "%s: stage 1 stopped at sample %ld (%s): from there '
           "the guarded estimate is stage 2's, without the paper's guarantee\\n\", argv[0], "
           f"st.stage1_lost_at, {P}_stage1_error_message(st.stage1_status));")
    failure = (f"status == {PU}_STAGE1 ? {P}_stage1_error_message(st.stage1_status) : "
               '"u has a NaN or inf, or y an inf"')
    return csv_main(name, banner, sizes, head=head, init=init, failure=failure, row=row,
                    prelude=prelude)


def guarded_makefile(name: str) -> str:
    """The ``Makefile``: ``make -C DIR`` builds ``DIR/<name>`` from both translation units.

    Parameters
    ----------
    name : str

    Returns
    -------
    str

    Examples
    --------
    >>> "g_main.c g.c g_stage1.c" in guarded_makefile("g")
    True
    """
    src = f"{name}_main.c {name}.c {name}_stage1.c"
    return (f"# Generated by thetahat codegen: builds the CSV harness {name} of {name}.c and "
            f"{name}_stage1.c.\n"
            "# Override e.g. CC=clang or CFLAGS='... -fsanitize=address,undefined'.\n"
            "CC ?= cc\n"
            f"CFLAGS ?= {' '.join(C_FLAGS)}\n"
            "LDLIBS ?= -lm\n\n"
            f"{name}: {src} {name}.h {name}_stage1.h\n"
            f"\t$(CC) $(CFLAGS) -o $@ {src} $(LDLIBS)\n\n"
            ".PHONY: clean\n"
            f"clean:\n\trm -f {name}\n")
