/*
 * The joint EKF of the augmented LuGre model (omega, z, theta), written by hand in C: the C
 * an engineer would write for a controller, the peer of the generated EKF in
 * bench_ekf_codegen.py. Same model, sampled-data map and filter as the filterpy peer
 * (peers.py: _f, _jac, _substeps, propagate_jacobian, run_ekf): RK4 sub-steps chosen from the
 * 2 x 2 Jacobian's eigenvalues (h rho <= 2), the input held over the sample, the exact
 * Jacobian of the RK4 map, a Joseph-form update of the measured omega, theta clipped to
 * [lo, hi] after each update. Fixed sizes, no heap.
 *
 * par = (J, sigma0, sigma1, alpha1, alpha2, omega0, theta_lo, theta_hi).
 */
#include <math.h>

#define NS 3
#define MAX_SUB 200

static void f(const double *par, double w, double z, double th, double u,
              double *dw, double *dz)
{
    double thc = th < par[6] ? par[6] : (th > par[7] ? par[7] : th);
    double zeta = thc + par[3] * exp(-(w / par[5]) * (w / par[5]));
    double phi = z * fabs(w) / zeta;
    *dw = (u - z - par[2] * (w - phi) - par[4] * w) / par[0];
    *dz = par[1] * (w - phi);
}

/* d(dw, dz)/d(w, z, theta): a 2 x 3 block, row-major (the theta row is zero). */
static void jac(const double *par, double w, double z, double th, double A[6])
{
    int inside = par[6] <= th && th <= par[7];
    double thc = th < par[6] ? par[6] : (th > par[7] ? par[7] : th);
    double strb = par[3] * exp(-(w / par[5]) * (w / par[5]));
    double zeta = thc + strb, dzeta = -2.0 * w / (par[5] * par[5]) * strb;
    double aw = fabs(w), sg = w > 0 ? 1.0 : (w < 0 ? -1.0 : 0.0);
    double phi_w = z * (sg * zeta - aw * dzeta) / (zeta * zeta);
    double phi_z = aw / zeta, phi_t = inside ? -z * aw / (zeta * zeta) : 0.0;
    A[0] = (-par[2] * (1.0 - phi_w) - par[4]) / par[0];
    A[1] = (-1.0 + par[2] * phi_z) / par[0];
    A[2] = par[2] * phi_t / par[0];
    A[3] = par[1] * (1.0 - phi_w);
    A[4] = -par[1] * phi_z;
    A[5] = -par[1] * phi_t;
}

static int substeps(const double *par, const double s[NS], double h)
{
    double A[6], tr, det, disc, rho;
    int n;
    jac(par, s[0], s[1], s[2], A);
    tr = A[0] + A[4];
    det = A[0] * A[4] - A[1] * A[3];
    disc = tr * tr - 4.0 * det;
    if (disc >= 0.0) {
        double r = sqrt(disc), a = fabs(0.5 * (tr + r)), b = fabs(0.5 * (tr - r));
        rho = a > b ? a : b;
    } else {
        rho = sqrt(fabs(det));
    }
    n = (int)ceil(h * rho / 2.0);
    return n < 1 ? 1 : (n > MAX_SUB ? MAX_SUB : n);
}

/* G = A (I + c K) for the 2 x 3 blocks A, K of 3 x 3 matrices whose theta row is zero. */
static void stage(const double A[6], const double K[6], double c, double G[6])
{
    int i, j;
    for (i = 0; i < 2; ++i)
        for (j = 0; j < 3; ++j)
            G[3 * i + j] = A[3 * i + j] + c * (A[3 * i] * K[j] + A[3 * i + 1] * K[3 + j]);
}

/* s <- the RK4 map over h with u held; F <- its Jacobian (3 x 3, row-major). */
static void propagate(const double *par, double s[NS], double u, double h, double F[9])
{
    int n = substeps(par, s, h), i, j, k;
    double dt = h / n, w = s[0], z = s[1], th = s[2];
    double A[6], K1[6], K2[6], K3[6], K4[6], M[9], T[9];
    for (i = 0; i < 9; ++i) F[i] = (i % 4 == 0) ? 1.0 : 0.0;
    for (k = 0; k < n; ++k) {
        double k1w, k1z, k2w, k2z, k3w, k3z, k4w, k4z, w2, z2, w3, z3, w4, z4;
        f(par, w, z, th, u, &k1w, &k1z);
        jac(par, w, z, th, K1);
        w2 = w + 0.5 * dt * k1w; z2 = z + 0.5 * dt * k1z;
        f(par, w2, z2, th, u, &k2w, &k2z);
        jac(par, w2, z2, th, A);
        stage(A, K1, 0.5 * dt, K2);
        w3 = w + 0.5 * dt * k2w; z3 = z + 0.5 * dt * k2z;
        f(par, w3, z3, th, u, &k3w, &k3z);
        jac(par, w3, z3, th, A);
        stage(A, K2, 0.5 * dt, K3);
        w4 = w + dt * k3w; z4 = z + dt * k3z;
        f(par, w4, z4, th, u, &k4w, &k4z);
        jac(par, w4, z4, th, A);
        stage(A, K3, dt, K4);
        /* F <- (I + dt/6 (K1 + 2 K2 + 2 K3 + K4)) F; the theta row of the bracket is e3 */
        for (i = 0; i < 9; ++i) M[i] = (i % 4 == 0) ? 1.0 : 0.0;
        for (i = 0; i < 6; ++i) M[i] += dt / 6.0 * (K1[i] + 2.0 * K2[i] + 2.0 * K3[i] + K4[i]);
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j)
                T[3 * i + j] = M[3 * i] * F[j] + M[3 * i + 1] * F[3 + j] + M[3 * i + 2] * F[6 + j];
        for (i = 0; i < 9; ++i) F[i] = T[i];
        w += dt / 6.0 * (k1w + 2.0 * k2w + 2.0 * k3w + k4w);
        z += dt / 6.0 * (k1z + 2.0 * k2z + 2.0 * k3z + k4z);
    }
    s[0] = w;
    s[1] = z;
}

/* The textbook shortcut: one forward-Euler step s <- s + h f(s), F = I + h df/ds (no
 * sub-steps; the discretisation error is O(h) where RK4's is O(h^4)). */
static void propagate_euler(const double *par, double s[NS], double u, double h, double F[9])
{
    double dw, dz, A[6];
    int i;
    f(par, s[0], s[1], s[2], u, &dw, &dz);
    jac(par, s[0], s[1], s[2], A);
    for (i = 0; i < 9; ++i) F[i] = (i % 4 == 0) ? 1.0 : 0.0;
    for (i = 0; i < 6; ++i) F[i] += h * A[i];
    s[0] += h * dw;
    s[1] += h * dz;
}

/* The filter over a record: sample 0 an update at (s0, P0); then predict over each interval
 * with the previous input held (RK4 map, or Euler's when euler != 0), update with y_k.
 * S (N x 3) receives s after each sample. Returns 0, or k + 1 where the state stopped being
 * finite. */
int peer_ekf_loop(const double *par, const double *Q, const double *P0, const double *s0,
                  double R, double h, const double *U, const double *Y, long N, double *S,
                  int euler)
{
    double s[NS], P[9], F[9], T[9], K[3], IKH[9];
    long k;
    int i, j, l;
    for (i = 0; i < NS; ++i) s[i] = s0[i];
    for (i = 0; i < 9; ++i) P[i] = P0[i];
    for (k = 0; k < N; ++k) {
        double Sy, nu;
        if (k) {
            if (euler)
                propagate_euler(par, s, U[k - 1], h, F);
            else
                propagate(par, s, U[k - 1], h, F);
            for (i = 0; i < 3; ++i)                        /* T = F P */
                for (j = 0; j < 3; ++j)
                    T[3 * i + j] = F[3 * i] * P[j] + F[3 * i + 1] * P[3 + j] + F[3 * i + 2] * P[6 + j];
            for (i = 0; i < 3; ++i)                        /* P = T F' + Q */
                for (j = 0; j < 3; ++j)
                    P[3 * i + j] = T[3 * i] * F[3 * j] + T[3 * i + 1] * F[3 * j + 1]
                                   + T[3 * i + 2] * F[3 * j + 2] + Q[3 * i + j];
        }
        Sy = P[0] + R;                                     /* H = (1, 0, 0) */
        for (i = 0; i < 3; ++i) K[i] = P[3 * i] / Sy;
        nu = Y[k] - s[0];
        for (i = 0; i < 3; ++i) s[i] += K[i] * nu;
        /* Joseph: P = (I - K H) P (I - K H)' + K R K' */
        for (i = 0; i < 9; ++i) IKH[i] = (i % 4 == 0) ? 1.0 : 0.0;
        for (i = 0; i < 3; ++i) IKH[3 * i] -= K[i];
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j) {
                double a = 0.0;
                for (l = 0; l < 3; ++l) a += IKH[3 * i + l] * P[3 * l + j];
                T[3 * i + j] = a;
            }
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j) {
                double a = 0.0;
                for (l = 0; l < 3; ++l) a += T[3 * i + l] * IKH[3 * j + l];
                P[3 * i + j] = a + K[i] * R * K[j];
            }
        s[2] = s[2] < par[6] ? par[6] : (s[2] > par[7] ? par[7] : s[2]);
        for (i = 0; i < NS; ++i) S[3 * k + i] = s[i];
        if (!isfinite(s[0]) || !isfinite(s[1]) || !isfinite(P[0])) return (int)(k + 1);
    }
    return 0;
}
