"""The fixed text around the printed EKF kernels: ``<name>.h``, the step, the CSV harness.

:func:`~thetahat.codegen.ekf_c.generate_ekf_c` prints the kernels; this module puts them in a
translation unit with the state struct, ``<name>_init`` and ``<name>_step`` (what
:func:`~thetahat.estimation.statistical.ekf_kernels.ekf_sample` does around the kernels: the
input check, the prediction after the first sample, the update where y is finite, the
divergence check) and writes the harness ``<name>_main.c`` (reads ``t,u…,y…`` CSV rows,
writes ``t,x̂…,θ̂…`` with 17 significant digits).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = ["csv_main", "ekf_header", "ekf_main", "ekf_source", "smooth_state"]


def ekf_header(name: str, banner: str, sizes: dict[str, Any]) -> str:
    """``<name>.h``: sizes, status codes, the state and the two functions.

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
    >>> "int e_step(e_state *st" in ekf_header("e", "", {"n": 2, "m": 1, "r": 1, "p": 1})
    True
    """
    P, PU = name, name.upper()
    n, m, r, p = sizes["n"], sizes["m"], sizes["r"], sizes["p"]
    N = n + p
    return banner + f"""#ifndef {PU}_H
#define {PU}_H

#ifdef __cplusplus
extern "C" {{
#endif

typedef double {P}_real_t;

enum {{ {PU}_NX = {n}, {PU}_NU = {m}, {PU}_NY = {r}, {PU}_NTHETA = {p}, {PU}_NS = {N} }};

/* What {P}_step returns. */
enum {P}_status {{
    {PU}_OK = 0,                /* the sample was processed */
    {PU}_NONFINITE_INPUT = 1,   /* NaN or inf in u, or inf in y: refused, state unchanged */
    {PU}_DIVERGED = 2           /* s or diag P is no longer finite: re-initialise */
}};

/* The filter's state: s = col(x_hat, theta_hat) (theta_hat in Theta), its covariance P
   (row-major), the last input stage 2 read (and under the hold "smooth" the history of
   its correction) and the samples processed. */
typedef struct {P}_state {{
    {P}_real_t s[{N}];
    {P}_real_t P[{N * N}];
    {P}_real_t u_prev[{max(m, 1)}];
{smooth_state(P, sizes)[0]}    long k;
}} {P}_state;

/* The prior: s and P before the first sample. */
void {P}_init({P}_state *st);
/* One sample: predict from the previous sample (none at the first), then update with y
   (none when y has a NaN: predicted over); theta_hat is clipped to Theta. */
int {P}_step({P}_state *st, const {P}_real_t u[], const {P}_real_t y[]);

#ifdef __cplusplus
}}
#endif

#endif /* {PU}_H */
"""


def smooth_state(P: str, sizes: dict[str, Any]) -> tuple[str, str]:
    """The hold "smooth"'s history in a state struct: its members (the last three raw samples,
    Σ (Δu)² and Σ (Δ²u)² per input) and the C statements that zero them in ``st``; two empty
    strings under another hold.

    Parameters
    ----------
    P : str
        The C prefix.
    sizes : dict
        m and the hold.

    Returns
    -------
    (str, str)
        The members, indented, one a line; the statements.

    Examples
    --------
    >>> members, zero = smooth_state("e", {"m": 2, "hold": "smooth"})
    >>> members.split()[:2], zero.splitlines()[0]
    (['e_real_t', 'u_hist[6];'], 'for (i = 0; i < 6; ++i) st->u_hist[i] = 0.0;')
    >>> smooth_state("e", {"m": 2, "hold": "foh"})
    ('', '')
    """
    m = sizes["m"]
    if sizes.get("hold") != "smooth" or m == 0:
        return "", ""
    return (f"    {P}_real_t u_hist[{3 * m}];    /* hold smooth: the last three raw u */\n"
            f"    {P}_real_t u_sums[{2 * m}];    /* and sum (du)^2, sum (d2u)^2 per input */\n",
            f"for (i = 0; i < {3 * m}; ++i) st->u_hist[i] = 0.0;\n    "
            f"for (i = 0; i < {2 * m}; ++i) st->u_sums[i] = 0.0;")


def ekf_source(name: str, banner: str, consts: Sequence[str], rhs: str, kernels: str, *,
               predict: str, update: str, samples: str, sizes: dict[str, Any]) -> str:
    """``<name>.c``: the data, f and its Jacobians, the printed kernels, init and step.

    Parameters
    ----------
    name, banner : str
    consts : sequence of str
        ``static const`` arrays (C_OUT, R_NOISE, …, S0, P0).
    rhs : str
        ``rhs_jac`` printed by SymPy.
    kernels : str
        The printed kernels (callees first).
    predict, update : str
        The calls of the printed ``ekf_predict`` and ``ekf_update``.
    samples : str
        The statements that set ``Ut`` from ``u``
        (:func:`~thetahat.codegen.ekf_c.input_samples`).
    sizes : dict
        n, m, r, p and the hold.

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

{chr(10).join(consts)}

{rhs}

{kernels}
void {P}_init({P}_state *st)
{{
    int i;
    for (i = 0; i < {N}; ++i) st->s[i] = S0[i];
    for (i = 0; i < {N * N}; ++i) st->P[i] = P0[i];
    for (i = 0; i < {max(m, 1)}; ++i) st->u_prev[i] = 0.0;
    {smooth_state(P, sizes)[1]}
    st->k = 0;
}}

int {P}_step({P}_state *st, const real_t u[], const real_t y[])
{{
    real_t U[{max(2 * m, 1)}];
    real_t Ut[{max(m, 1)}], Raw[{max(m, 1)}];
    real_t Phi[{n * n}];
    real_t Gam[{n * p}];
    real_t Y[{r}];
    int i, finite_y = 1;
    for (i = 0; i < {m}; ++i)
        if (!isfinite(u[i])) return {PU}_NONFINITE_INPUT;
    for (i = 0; i < {r}; ++i)
        if (isinf(y[i])) return {PU}_NONFINITE_INPUT;
    {samples}
    if (st->k > 0) {{
        for (i = 0; i < {m}; ++i) {{
            U[i] = st->u_prev[i];
            U[{m} + i] = Ut[i];
        }}
        {predict};
    }}
    for (i = 0; i < {r}; ++i) {{
        Y[i] = y[i];
        if (isnan(y[i])) finite_y = 0;
    }}
    if (finite_y) (void){update};
    for (i = 0; i < {N}; ++i)
        if (!isfinite(st->s[i]) || !isfinite(st->P[i * {N} + i])) return {PU}_DIVERGED;
    for (i = 0; i < {m}; ++i) st->u_prev[i] = Ut[i];
    st->k += 1;
    (void)U; (void)Ut; (void)Raw; (void)Phi; (void)Gam;
    return {PU}_OK;
}}
"""


def ekf_main(name: str, banner: str, sizes: dict[str, Any]) -> str:
    """``<name>_main.c``: ``<name> DATA.csv`` reads rows ``t,u_1…u_m,y_1…y_r`` after a header
    line and writes ``t,x_hat_1…,theta_hat_1…`` rows to stdout; exit 1 on a bad row or
    file, 2 on a refused sample or a divergence (the row named on stderr).

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
    >>> "e_step(&st, u, y)" in ekf_main("e", "", {"n": 2, "m": 1, "r": 1, "p": 1})
    True
    """
    P, PU = name, name.upper()
    n, m, r, p = sizes["n"], sizes["m"], sizes["r"], sizes["p"]
    head = ",".join(["t", *(f"x_hat_{i + 1}" for i in range(n)),
                     *(f"theta_hat_{i + 1}" for i in range(p))])
    return csv_main(name, banner, sizes, head=head, init=f"{P}_init(&st);",
                    failure=(f'status == {PU}_DIVERGED ? "the EKF diverged" : '
                             '"u has a NaN or inf, or y an inf"'),
                    row=f'for (i = 0; i < {n + p}; ++i) printf(",%.17g", st.s[i]);')


def csv_main(name: str, banner: str, sizes: dict[str, Any], *, head: str, init: str,
             failure: str, row: str, prelude: str = "") -> str:
    """A CSV harness around ``<name>_step(&st, u, y)``: rows ``t,u…,y…`` after a header line
    in, ``t`` and the estimates out (17 significant digits); exit 1 on a bad row or file, 2 on
    a sample ``<name>_step`` refuses (the row and why on stderr).

    Parameters
    ----------
    name, banner : str
    sizes : dict
        m and r.
    head : str
        The output's header line.
    init : str
        C statements that start ``st`` (they may ``return 1``).
    failure : str
        A C expression of the message for a nonzero ``status``.
    row : str
        C statements that print the estimates after ``t`` (``i`` is free).
    prelude : str
        C text before ``main`` (helpers).

    Returns
    -------
    str

    Examples
    --------
    >>> text = csv_main("e", "", {"m": 1, "r": 1}, head="t,x", init="e_init(&st);",
    ...                 failure='"refused"', row='printf(",%.17g", st.s[0]);')
    >>> "status = e_step(&st, u, y);" in text
    True
    """
    P = name
    m, r = sizes["m"], sizes["r"]
    return banner + f"""#include <stdio.h>
#include <stdlib.h>
#include "{P}.h"

#define NCOL {1 + m + r}
{prelude}
int main(int argc, char **argv)
{{
    char line[65536];
    {P}_real_t row[NCOL], u[{max(m, 1)}], y[{r}];
    {P}_state st;
    long k = 0;
    int i, status;
    FILE *in;
    if (argc != 2) {{
        fprintf(stderr, "usage: %s DATA.csv (columns t,u_1..u_{m},y_1..y_{r}, a header)\\n",
                argv[0]);
        return 1;
    }}
    in = fopen(argv[1], "r");
    if (in == NULL || fgets(line, sizeof line, in) == NULL) {{
        fprintf(stderr, "%s: cannot read %s\\n", argv[0], argv[1]);
        return 1;
    }}
    {init}
    printf("{head}\\n");
    while (fgets(line, sizeof line, in) != NULL) {{
        char *p = line, *end;
        for (i = 0; i < NCOL; ++i) {{
            row[i] = strtod(p, &end);
            if (end == p || (i < NCOL - 1 && *end != ',')) {{
                fprintf(stderr, "%s: data row %ld: expected %d numbers\\n", argv[0], k + 1,
                        NCOL);
                fclose(in);
                return 1;
            }}
            p = end + 1;
        }}
        for (i = 0; i < {m}; ++i) u[i] = row[1 + i];
        for (i = 0; i < {r}; ++i) y[i] = row[{1 + m} + i];
        status = {P}_step(&st, u, y);
        if (status != 0) {{
            fprintf(stderr, "%s: data row %ld: %s\\n", argv[0], k + 1, {failure});
            fclose(in);
            return 2;
        }}
        printf("%.17g", row[0]);
        {row}
        printf("\\n");
        ++k;
    }}
    fclose(in);
    return 0;
}}
"""
