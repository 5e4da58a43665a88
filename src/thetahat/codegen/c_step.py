"""One observer step as C text, stage by stage as in :func:`thetahat.estimation.step.advance`.

:func:`step_source` assembles the ``.c`` body from the stages below; each is named after the
paper's equation it computes and mirrors one stage of the Python step:

* ``samples``: NaN in y marks a missing sample (``nan_policy``), inf or NaN elsewhere is refused;
* ``forcing_3ab``: F = right-hand side of (3a)–(3b) on (x̂, z), φ̂ = g + z (3c), ∂g/∂x;
* ``update_law_8``: θ̂ after the step, the law's exact step then the projection onto the box Θ;
* ``theta_term_3b``: z receives −∂g/∂θ Δθ̂ (the first term of (3b));
* ``jacobian_part``: N = [[E ∂g/∂x, 0], [∂g/∂x K_x C, 0]] of the linearly implicit step;
* ``second_observer_vi``: x̂₂ of Sec. VI, driven by θ̂ at the start of the step;
* ``implicit_exponential_step``: s⁺ = s + (I − γΦ₁N)⁻¹Φ₁F (``discretize``), γ = 1/2.

The text uses ``$P`` for the observer's prefix; ``real_t``, ``EXP`` and friends are defined by
the generated file for the chosen precision.
"""

from __future__ import annotations

from dataclasses import dataclass
from string import Template

from .c_linalg import EXPM, LINALG

__all__ = ["StepOptions", "step_source"]


@dataclass(frozen=True, slots=True)
class StepOptions:
    """What the generated step contains (decided by :func:`~thetahat.codegen.generate_c`).

    Attributes
    ----------
    prefix : str
        C prefix of the public names.
    law : {"constant", "algebraic", "intermittent", "gradient"}
    freeze : bool
        ``on_invalid == "freeze"`` (θ* invalid: l = 0) instead of an error code.
    skip : bool
        ``nan_policy == "skip"``: predict over a sample whose y holds NaN.
    second : bool
        A second observer is attached.
    on_estimates : bool
        The second observer evaluates g on C x̂₂.
    """

    prefix: str
    law: str
    freeze: bool
    skip: bool
    second: bool
    on_estimates: bool

    @property
    def needs_dg_dv(self) -> bool:
        """∂g/∂v is used (prediction over missing samples, or g on the estimates)."""
        return self.skip or (self.second and self.on_estimates)


_LAW_CONSTANT = r"""
/* (8), ConstantLaw: theta_hat is held (projected onto Theta should it lie outside). */
static int update_law_8(const real_t v[], const real_t x[], const real_t phi[],
                        const real_t th[], const real_t g[], const real_t Gth[],
                        real_t th_next[])
{
    int i;
    (void)v;
    (void)x;
    (void)phi;
    (void)g;
    (void)Gth;
    for (i = 0; i < NP; ++i) {
        th_next[i] = into_box(th[i], th[i], THETA_LOWER[i], THETA_UPPER[i]);
    }
    return ${PU}_OK;
}
"""

_RAMP = r"""
/* smooth_ramp(low, high) of ||phi_hat|| (Remark 5): 0 below low, 1 above high, 3t^2 - 2t^3. */
static real_t excitation_weight(const real_t phi[])
{
    real_t big = 0, safe, acc = 0, t;
    int a;
    for (a = 0; a < NK; ++a) {
        big = FABS(phi[a]) > big ? FABS(phi[a]) : big;
    }
    safe = big > 0 ? big : 1;
    for (a = 0; a < NK; ++a) {
        acc += (phi[a] / safe) * (phi[a] / safe);
    }
    t = (big * SQRT(acc) - RAMP_LOW) / (RAMP_HIGH - RAMP_LOW);
    t = t < 0 ? 0 : (t > 1 ? 1 : t);
    t = t * t * (3 - 2 * t);
    return t < 0 ? 0 : (t > 1 ? 1 : t);
}
"""

_LAW_INVERSION = r"""
/* (8), Propositions 1-2: exact flow of theta' = l Gamma (theta* - theta) over dt with theta*
 * held, theta* + exp(-l Gamma dt) (theta_hat - theta*), then the projection onto Theta.
 * theta* is evaluated only where l > 0: where l = 0 the law does not use it (so, e.g., no
 * 0/0 is computed at phi_hat = 0). */
static int update_law_8(const real_t v[], const real_t x[], const real_t phi[],
                        const real_t th[], const real_t g[], const real_t Gth[],
                        real_t th_next[])
{
    real_t lw, ts[NP], target, decay;
    int i;
    (void)g;
    (void)Gth;
    for (i = 0; i < NP; ++i) {
        ts[i] = th[i];
    }
    lw = $WEIGHT;
    if (lw > 0) {
        theta_star(v, x, phi, ts);
        for (i = 0; i < NP; ++i) {
            if (!isfinite(ts[i])) {
                $INVALID
            }
        }
    }
    for (i = 0; i < NP; ++i) {
        target = lw > 0 ? ts[i] : th[i];
        decay = EXP(-lw * DT * GAMMA[i]);
        th_next[i] = into_box(target - decay * (target - th[i]), th[i], THETA_LOWER[i],
                              THETA_UPPER[i]);
    }
    return ${PU}_OK;
}
"""

_LAW_GRADIENT = r"""
/* (8), Propositions 3-4 with M = (dg/dtheta)^T: exponential Euler step of the linearised law
 * theta' = f - K (theta - theta_hat), f = Gamma M (phi_hat - g), K = Gamma M dg/dtheta, then
 * the projection onto Theta (GradientInversion.step). */
static int update_law_8(const real_t v[], const real_t x[], const real_t phi[],
                        const real_t th[], const real_t g[], const real_t Gth[],
                        real_t th_next[])
{
    enum { Q = NP + 1 };
    real_t GM[NP * NK], f[NP], Z[Q * Q], Ex[Q * Q], acc, delta;
    int a, b, c, ok = 1;
    (void)v;
    (void)x;
    for (a = 0; a < NP; ++a) {
        for (b = 0; b < NK; ++b) {
            GM[a * NK + b] = GAMMA[a] * Gth[b * NP + a];
        }
    }
    for (a = 0; a < NP; ++a) {
        acc = 0;
        for (b = 0; b < NK; ++b) {
            acc += GM[a * NK + b] * (phi[b] - g[b]);
        }
        f[a] = acc;
        for (c = 0; c < NP; ++c) {
            acc = 0;
            for (b = 0; b < NK; ++b) {
                acc += GM[a * NK + b] * Gth[b * NP + c];
            }
            Z[a * Q + c] = -DT * acc;
            ok = ok && isfinite(Z[a * Q + c]);
        }
        Z[a * Q + NP] = DT * f[a];
        ok = ok && isfinite(Z[a * Q + NP]);
    }
    for (c = 0; c < Q; ++c) {
        Z[NP * Q + c] = 0;
    }
    if (!ok) {
        for (c = 0; c < Q * Q; ++c) {
            Z[c] = 0;
        }
    }
    expm_small(Z, Ex);
    for (a = 0; a < NP; ++a) {
        ok = ok && isfinite(Ex[a * Q + NP]);
    }
    for (a = 0; a < NP; ++a) {
        if (ok) {
            delta = Ex[a * Q + NP];
        } else if (isfinite(f[a])) {
            delta = DT * f[a];
        } else if (f[a] > 0) {
            delta = THETAHAT_FAR;
        } else if (f[a] < 0) {
            delta = -THETAHAT_FAR;
        } else {
            delta = 0;
        }
        th_next[a] = into_box(th[a] + delta, th[a], THETA_LOWER[a], THETA_UPPER[a]);
    }
    return ${PU}_OK;
}
"""

_FORCING = r"""
/* (3a)-(3b) on (x_hat, z) without the theta term, and phi_hat = g + z (3c):
 * F_x = A x_hat + B u + E phi_hat + K_x y~,  F_z = K_phi y~ - dg/dx K_x y~,  y~ = y - C x_hat. */
static void forcing_3ab(const real_t x[], const real_t u[], const real_t y[],
                        const real_t phi[], const real_t Gx[], real_t F[])
{
    real_t innov[NY], kin[NX], acc;
    int i, j, a;
    for (i = 0; i < NY; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += C[i * NX + j] * x[j];
        }
        innov[i] = y[i] - acc;
    }
    for (i = 0; i < NX; ++i) {
        acc = 0;
        for (j = 0; j < NY; ++j) {
            acc += KX[i * NY + j] * innov[j];
        }
        kin[i] = acc;
    }
    for (i = 0; i < NX; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += A[i * NX + j] * x[j];
        }
        for (j = 0; j < NU; ++j) {
            acc += B[i * NUB + j] * u[j];
        }
        for (a = 0; a < NK; ++a) {
            acc += E[i * NK + a] * phi[a];
        }
        F[i] = acc + kin[i];
    }
    for (a = 0; a < NK; ++a) {
        acc = 0;
        for (j = 0; j < NY; ++j) {
            acc += KPHI[a * NY + j] * innov[j];
        }
        for (j = 0; j < NX; ++j) {
            acc -= Gx[a * NX + j] * kin[j];
        }
        F[NX + a] = acc;
    }
}

/* The first term of (3b): z receives -dg/dtheta (theta_hat+ - theta_hat) / dt. */
static void theta_term_3b(const real_t Gth[], const real_t th[], const real_t th_next[],
                          real_t F[])
{
    real_t acc;
    int a, j, moving = 0;
    for (j = 0; j < NP; ++j) {
        moving = moving || th_next[j] != th[j];
    }
    if (!moving) {
        return;
    }
    for (a = 0; a < NK; ++a) {
        acc = 0;
        for (j = 0; j < NP; ++j) {
            acc += Gth[a * NP + j] * (th_next[j] - th[j]);
        }
        F[NX + a] += -acc / DT;
    }
}

/* N = [[E dg/dx, 0], [dg/dx K_x C, 0]]: the state-dependent Jacobian part of the step. */
static void jacobian_part(const real_t Gx[], real_t N[])
{
    real_t acc;
    int i, j, a, l;
    for (i = 0; i < NZ * NZ; ++i) {
        N[i] = 0;
    }
    for (i = 0; i < NX; ++i) {
        for (j = 0; j < NX; ++j) {
            acc = 0;
            for (a = 0; a < NK; ++a) {
                acc += E[i * NK + a] * Gx[a * NX + j];
            }
            N[i * NZ + j] = acc;
        }
    }
    for (a = 0; a < NK; ++a) {
        for (j = 0; j < NX; ++j) {
            acc = 0;
            for (l = 0; l < NX; ++l) {
                acc += Gx[a * NX + l] * KXC[l * NX + j];
            }
            N[(NX + a) * NZ + j] = acc;
        }
    }
}
"""

_PREDICT = r"""
/* A missing sample (nan_policy = "skip"): predict with y = C x_hat, theta_hat frozen, z constant:
 * F = col(A x_hat + B u + E phi_hat, 0), N = [[E (dg/dx + dg/dy C), 0], [0, 0]]. */
static void forcing_predict(const real_t v[], const real_t x[], const real_t th[],
                            const real_t phi[], const real_t Gx[], real_t F[], real_t N[])
{
    real_t g_[NK], Gx_[NK * NX], Gv[NK * NV], J[NK * NX], acc;
    int i, j, a, l;
    g_dx_dv(v, x, th, g_, Gx_, Gv);
    for (a = 0; a < NK; ++a) {
        for (j = 0; j < NX; ++j) {
            acc = 0;
            for (l = 0; l < NY; ++l) {
                acc += Gv[a * NV + NU + l] * C[l * NX + j];
            }
            J[a * NX + j] = Gx[a * NX + j] + acc;
        }
    }
    for (i = 0; i < NZ * NZ; ++i) {
        N[i] = 0;
    }
    for (i = 0; i < NX; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += A[i * NX + j] * x[j];
        }
        for (j = 0; j < NU; ++j) {
            acc += B[i * NUB + j] * v[j];
        }
        for (a = 0; a < NK; ++a) {
            acc += E[i * NK + a] * phi[a];
        }
        F[i] = acc;
        for (j = 0; j < NX; ++j) {
            acc = 0;
            for (a = 0; a < NK; ++a) {
                acc += E[i * NK + a] * J[a * NX + j];
            }
            N[i * NZ + j] = acc;
        }
    }
    for (a = 0; a < NK; ++a) {
        F[NX + a] = 0;
    }
}
"""

_SECOND = r"""
/* Second observer of Sec. VI, with theta_hat at the start of the step:
 * x2' = A x2 + B u + E g(v2, x2, theta_hat) + K_x2 (y - C x2), v2 = col(u, y or C x2);
 * N = E (dg/dx [+ dg/dy C when g runs on the estimates]). */
static int second_observer_vi(const real_t x2[], const real_t u[], const real_t y[],
                              const real_t th[], int correct, real_t x2_next[])
{
    real_t yhat[NY], v2[NV], g2[NK], Gx2[NK * NX], F2[NX], N2[NX * NX], acc;
    int i, j, a, on_est = $ON_ESTIMATES || !correct;
    $GV_DECL
    for (i = 0; i < NY; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += C[i * NX + j] * x2[j];
        }
        yhat[i] = acc;
    }
    for (i = 0; i < NU; ++i) {
        v2[i] = u[i];
    }
    for (i = 0; i < NY; ++i) {
        v2[NU + i] = on_est ? yhat[i] : y[i];
    }
    $G2_CALL
    $GV_TERM
    for (i = 0; i < NX; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += A[i * NX + j] * x2[j];
        }
        for (j = 0; j < NU; ++j) {
            acc += B[i * NUB + j] * u[j];
        }
        for (a = 0; a < NK; ++a) {
            acc += E[i * NK + a] * g2[a];
        }
        F2[i] = acc;
        if (correct) {
            acc = 0;
            for (j = 0; j < NY; ++j) {
                acc += K2[i * NY + j] * (y[j] - yhat[j]);
            }
            F2[i] += acc;
        }
        for (j = 0; j < NX; ++j) {
            acc = 0;
            for (a = 0; a < NK; ++a) {
                acc += E[i * NK + a] * Gx2[a * NX + j];
            }
            N2[i * NX + j] = acc;
        }
    }
    return implicit_exponential_step(NX, $PHI12_CHOICE, N2, F2, x2, x2_next);
}
"""

_GV_DECL = "real_t Gv2[NK * NV];"
_GV_TERM = r"""if (on_est) {
        for (a = 0; a < NK; ++a) {
            for (j = 0; j < NX; ++j) {
                acc = 0;
                for (i = 0; i < NY; ++i) {
                    acc += Gv2[a * NV + NU + i] * C[i * NX + j];
                }
                Gx2[a * NX + j] += acc;
            }
        }
    }"""

_ADVANCE = r"""
/* One step of observer (3), law (8) [and the second observer] from *s with the samples
 * (u, y) held over dt, into *out (thetahat.estimation.step.advance, zero-order hold). */
static int advance(const ${P}_state *s, const real_t u[], const real_t y[], int correct,
                   ${P}_state *out)
{
    const real_t *x = s->x_hat, *z = s->z, *th = s->theta_hat;
    real_t v[NV], g[NK], Gx[NK * NX], Gth[NK * NP], phi[NK], F[NZ], N[NZ * NZ], xz[NZ],
        xz_next[NZ], acc;
    int i, j, a, status;
    for (i = 0; i < NU; ++i) {
        v[i] = u[i];
    }
    for (i = 0; i < NY; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += C[i * NX + j] * x[j];
        }
        v[NU + i] = correct ? y[i] : acc;
    }
    g_and_jacobians(v, x, th, g, Gx, Gth);
    for (a = 0; a < NK; ++a) {
        phi[a] = g[a] + z[a];
    }
    if (correct) {
        forcing_3ab(x, u, y, phi, Gx, F);
        status = update_law_8(v, x, phi, th, g, Gth, out->theta_hat);
        if (status != ${PU}_OK) {
            return status;
        }
        theta_term_3b(Gth, th, out->theta_hat, F);
        jacobian_part(Gx, N);
    } else {
        $PREDICT_CALL
    }
    $SECOND_CALL
    for (i = 0; i < NX; ++i) {
        xz[i] = x[i];
    }
    for (a = 0; a < NK; ++a) {
        xz[NX + a] = z[a];
    }
    if (implicit_exponential_step(NZ, $PHI1_CHOICE, N, F, xz, xz_next) != 0) {
        return ${PU}_ERR_DIVERGED;
    }
    for (i = 0; i < NX; ++i) {
        out->x_hat[i] = xz_next[i];
    }
    for (a = 0; a < NK; ++a) {
        out->z[a] = xz_next[NX + a];
    }
    return ${PU}_OK;
}
"""

_PUBLIC = r"""
/* The samples: NaN in y marks a missing sample (nan_policy); NaN or inf in u and inf in y are
 * refused. Returns ${PU}_OK with *correct set, or an error code. */
static int samples(const real_t u[], const real_t y[], int *correct)
{
    int i;
    *correct = 1;
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
            *correct = 0;
        }
    }
    return (*correct || $SKIP) ? ${PU}_OK : ${PU}_ERR_MISSING;
}

static int all_finite(const real_t a[], int size)
{
    int i;
    for (i = 0; i < size; ++i) {
        if (!isfinite(a[i])) {
            return 0;
        }
    }
    return 1;
}

/* Sum of squares of a[0..size) added to acc (NaN and inf propagate). */
static real_t add_squares(real_t acc, const real_t a[], int size)
{
    int i;
    for (i = 0; i < size; ++i) {
        acc += a[i] * a[i];
    }
    return acc;
}

int ${P}_init(${P}_state *s, const real_t theta_hat0[], const real_t x_hat0[])
{
    const real_t *th = theta_hat0 != 0 ? theta_hat0 : THETA_HAT0;
    const real_t *x0 = x_hat0 != 0 ? x_hat0 : X_HAT0;
    real_t big = 1, dist2 = 0, d, tol;
    int i;
    if (!all_finite(th, NP) || !all_finite(x0, NX)) {
        return ${PU}_ERR_INIT;
    }
    for (i = 0; i < NP; ++i) {
        big = FABS(th[i]) > big ? FABS(th[i]) : big;
        d = th[i] < THETA_LOWER[i] ? THETA_LOWER[i] - th[i]
            : (th[i] > THETA_UPPER[i] ? th[i] - THETA_UPPER[i] : 0);
        dist2 += d * d;
    }
    tol = INIT_RTOL * big;
    if (!(SQRT(dist2) <= tol)) {
        return ${PU}_ERR_INIT;
    }
    for (i = 0; i < NP; ++i) {
        s->theta_hat[i] = into_box(th[i], th[i], THETA_LOWER[i], THETA_UPPER[i]);
    }
    for (i = 0; i < NX; ++i) {
        s->x_hat[i] = x0[i];
    }
    for (i = 0; i < NK; ++i) {
        s->z[i] = 0;
    }
    $INIT_SECOND
    return ${PU}_OK;
}

int ${P}_step(${P}_state *s, const real_t u[], const real_t y[])
{
    ${P}_state next;
    real_t norm2;
    int correct, status;
    status = samples(u, y, &correct);
    if (status != ${PU}_OK) {
        return status;
    }
    status = advance(s, u, y, correct, &next);
    if (status != ${PU}_OK) {
        return status;
    }
    /* step.diverged: the new state's norm exceeds DIVERGENCE_BOUND, or is NaN or inf */
    norm2 = add_squares(add_squares(add_squares(0, next.x_hat, NX), next.z, NK),
                        next.theta_hat, NP);
    $NORM_SECOND
    if (!(norm2 <= DIVERGENCE_BOUND * DIVERGENCE_BOUND)) {
        return ${PU}_ERR_DIVERGED;
    }
    *s = next;
    return ${PU}_OK;
}

int ${P}_phi_hat(const ${P}_state *s, const real_t u[], const real_t y[], real_t phi_hat[])
{
    real_t v[NV], g[NK], acc;
    int i, j, a, correct, status;
    status = samples(u, y, &correct);
    if (status != ${PU}_OK) {
        return status;
    }
    for (i = 0; i < NU; ++i) {
        v[i] = u[i];
    }
    for (i = 0; i < NY; ++i) {
        acc = 0;
        for (j = 0; j < NX; ++j) {
            acc += C[i * NX + j] * s->x_hat[j];
        }
        v[NU + i] = correct ? y[i] : acc;
    }
    g_only(v, s->x_hat, s->theta_hat, g);
    for (a = 0; a < NK; ++a) {
        phi_hat[a] = g[a] + s->z[a];
    }
    return ${PU}_OK;
}

const real_t *${P}_x_hat(const ${P}_state *s)
{
    return s->x_hat;
}

const real_t *${P}_theta_hat(const ${P}_state *s)
{
    return s->theta_hat;
}
$ACCESS_SECOND
const char *${P}_error_message(int status)
{
    switch (status) {
    case ${PU}_OK:
        return "ok";
    case ${PU}_ERR_INPUT:
        return "u holds NaN or inf, or y holds inf (only NaN marks a missing y)";
    case ${PU}_ERR_MISSING:
        return "y holds NaN and nan_policy='raise'; build the observer with nan_policy='skip' "
               "to predict over missing samples, or clean the data";
    case ${PU}_ERR_THETA_STAR:
        return "theta* is NaN or inf where the excitation weight is positive and "
               "on_invalid='raise'; make l vanish there or use on_invalid='freeze'";
    case ${PU}_ERR_DIVERGED:
        return "the observer state would diverge (norm above the bound, NaN or inf): the gains "
               "are too high for this dt (decrease dt or increase eps), or the data scaling is "
               "off; the state is unchanged";
    case ${PU}_ERR_INIT:
        return "theta_hat0 lies outside Theta, or theta_hat0 / x_hat0 is not finite";
    default:
        return "unknown status";
    }
}
"""


def step_source(opts: StepOptions) -> str:
    """The stages, the step and the public functions of the ``.c`` file (after the constants).

    Parameters
    ----------
    opts : StepOptions

    Returns
    -------
    str

    Examples
    --------
    >>> text = step_source(StepOptions(prefix="obs", law="gradient", freeze=False, skip=False,
    ...                                second=False, on_estimates=False))
    >>> "int obs_step(obs_state *s" in text and "malloc" not in text
    True
    """
    parts = [LINALG]
    if opts.law == "constant":
        parts.append(_LAW_CONSTANT)
    elif opts.law == "gradient":
        parts += [EXPM, _LAW_GRADIENT]
    else:
        if opts.law == "intermittent":
            parts.append(_RAMP)
        invalid = "lw = 0;" if opts.freeze else "return ${PU}_ERR_THETA_STAR;"
        weight = "excitation_weight(phi)" if opts.law == "intermittent" else "1"
        parts.append(Template(_LAW_INVERSION).safe_substitute(INVALID=invalid, WEIGHT=weight))
    parts.append(_FORCING)
    if opts.skip:
        parts.append(_PREDICT)
    if opts.second:
        parts.append(Template(_SECOND).safe_substitute(
            ON_ESTIMATES="1" if opts.on_estimates else "0",
            GV_DECL=_GV_DECL if opts.needs_dg_dv else "",
            GV_TERM=_GV_TERM if opts.needs_dg_dv else "",
            G2_CALL=("g_dx_dv(v2, x2, th, g2, Gx2, Gv2);" if opts.needs_dg_dv
                     else "g_and_dg_dx(v2, x2, th, g2, Gx2);"),
            PHI12_CHOICE="correct ? PHI12 : PHI12_OPEN" if opts.skip else "PHI12"))
    predict = ("for (j = 0; j < NP; ++j) {\n            out->theta_hat[j] = th[j];\n        }\n"
               "        forcing_predict(v, x, th, phi, Gx, F, N);") if opts.skip else \
        "return ${PU}_ERR_MISSING;"
    second_call = ("if (second_observer_vi(s->x_hat_refined, u, y, th, correct, "
                   "out->x_hat_refined) != 0) {\n        return ${PU}_ERR_DIVERGED;\n    }"
                   if opts.second else "")
    parts.append(Template(_ADVANCE).safe_substitute(
        PREDICT_CALL=predict, SECOND_CALL=second_call,
        PHI1_CHOICE="correct ? PHI1 : PHI1_OPEN" if opts.skip else "PHI1"))
    access = ("\nconst real_t *${P}_x_hat_refined(const ${P}_state *s)\n{\n"
              "    return s->x_hat_refined;\n}\n" if opts.second else "")
    parts.append(Template(_PUBLIC).safe_substitute(
        SKIP="1" if opts.skip else "0",
        INIT_SECOND=("for (i = 0; i < NX; ++i) {\n        s->x_hat_refined[i] = x0[i];\n    }"
                     if opts.second else ""),
        NORM_SECOND=("norm2 = add_squares(norm2, next.x_hat_refined, NX);" if opts.second
                     else ""),
        ACCESS_SECOND=access))
    text = "".join(parts)
    return Template(text).safe_substitute(P=opts.prefix, PU=opts.prefix.upper())
