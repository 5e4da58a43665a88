"""The dependency-free numerics of the generated step, as C text (used by :mod:`.c_step`).

``LINALG``: Gaussian elimination with partial pivoting (never divides by zero), the linearly
implicit exponential step of :mod:`thetahat.estimation.discretize` for a zero-order hold, and
the projection of a candidate onto the box Θ (NaN → θ̂, a clip to ±FAR, then to the box).
``EXPM``: exp of the small (p + 1) × (p + 1) matrix of the gradient law's exponential Euler
step (Taylor series of degree 20 with scaling and squaring, as the numba kernel).
"""

from __future__ import annotations

__all__ = ["EXPM", "LINALG"]

LINALG = r"""
/* Gaussian elimination with partial pivoting of the q x q row-major M; b becomes the solution.
 * Returns 0, or 1 for an exactly singular matrix (never divides by zero). */
static int solve(int q, real_t M[], real_t b[])
{
    int c, i, j, piv;
    real_t best, f, tmp, acc;
    for (c = 0; c < q; ++c) {
        piv = c;
        best = FABS(M[c * q + c]);
        for (i = c + 1; i < q; ++i) {
            if (FABS(M[i * q + c]) > best) {
                best = FABS(M[i * q + c]);
                piv = i;
            }
        }
        if (!(best > 0)) {
            return 1;
        }
        if (piv != c) {
            for (j = 0; j < q; ++j) {
                tmp = M[c * q + j];
                M[c * q + j] = M[piv * q + j];
                M[piv * q + j] = tmp;
            }
            tmp = b[c];
            b[c] = b[piv];
            b[piv] = tmp;
        }
        for (i = c + 1; i < q; ++i) {
            f = M[i * q + c] / M[c * q + c];
            for (j = c + 1; j < q; ++j) {
                M[i * q + j] -= f * M[c * q + j];
            }
            b[i] -= f * b[c];
        }
    }
    for (c = q - 1; c >= 0; --c) {
        acc = b[c];
        for (j = c + 1; j < q; ++j) {
            acc -= M[c * q + j] * b[j];
        }
        b[c] = acc / M[c * q + c];
    }
    return 0;
}

/* discretize.linearly_implicit_exponential_step (zero-order hold):
 * s+ = s + (I - IMPLICITNESS Phi1 N)^-1 Phi1 F, with Phi1 = h phi1(h L) for the fixed dt. */
static int implicit_exponential_step(int q, const real_t Phi1[], const real_t N[],
                                     const real_t F[], const real_t s[], real_t out[])
{
    real_t M[NZ * NZ], rhs[NZ], acc;
    int i, j, l;
    for (i = 0; i < q; ++i) {
        acc = 0;
        for (j = 0; j < q; ++j) {
            acc += Phi1[i * q + j] * F[j];
        }
        rhs[i] = acc;
        for (j = 0; j < q; ++j) {
            acc = 0;
            for (l = 0; l < q; ++l) {
                acc += Phi1[i * q + l] * N[l * q + j];
            }
            M[i * q + j] = acc * -IMPLICITNESS;
        }
        M[i * q + i] += 1;
    }
    if (solve(q, M, rhs) != 0) {
        return 1;
    }
    for (i = 0; i < q; ++i) {
        out[i] = s[i] + rhs[i];
    }
    return 0;
}

/* law_base.finite_candidate, then the projection onto the box (a clip: diagonal Gamma). */
static real_t into_box(real_t c, real_t fallback, real_t lo, real_t hi)
{
    if (c != c) {
        c = fallback;
    }
    c = c < -THETAHAT_FAR ? -THETAHAT_FAR : (c > THETAHAT_FAR ? THETAHAT_FAR : c);
    return c < lo ? lo : (c > hi ? hi : c);
}
"""

EXPM = r"""
/* exp(Z) of the (NP+1) x (NP+1) matrix Z: Taylor series of degree 20 after scaling ||Z||_1
 * below 1/2, then squaring (the step is a small matrix: dt times the law's gain). */
static void expm_small(const real_t Z[], real_t E[])
{
    enum { Q = NP + 1 };
    real_t T[Q * Q], U[Q * Q], nrm = 0, col, scale = 1, acc;
    int i, j, l, deg, squarings = 0;
    for (j = 0; j < Q; ++j) {
        col = 0;
        for (i = 0; i < Q; ++i) {
            col += FABS(Z[i * Q + j]);
        }
        nrm = col > nrm ? col : nrm;
    }
    while (nrm * scale > 0.5 && squarings < 1100) {
        scale *= 0.5;
        ++squarings;
    }
    for (i = 0; i < Q * Q; ++i) {
        T[i] = (i % (Q + 1) == 0) ? 1 : 0;
        E[i] = T[i];
    }
    for (deg = 1; deg <= 20; ++deg) {
        for (i = 0; i < Q; ++i) {
            for (j = 0; j < Q; ++j) {
                acc = 0;
                for (l = 0; l < Q; ++l) {
                    acc += T[i * Q + l] * Z[l * Q + j];
                }
                U[i * Q + j] = acc * scale / deg;
            }
        }
        for (i = 0; i < Q * Q; ++i) {
            T[i] = U[i];
            E[i] += U[i];
        }
    }
    for (deg = 0; deg < squarings; ++deg) {
        for (i = 0; i < Q; ++i) {
            for (j = 0; j < Q; ++j) {
                acc = 0;
                for (l = 0; l < Q; ++l) {
                    acc += E[i * Q + l] * E[l * Q + j];
                }
                U[i * Q + j] = acc;
            }
        }
        for (i = 0; i < Q * Q; ++i) {
            E[i] = U[i];
        }
    }
}
"""
