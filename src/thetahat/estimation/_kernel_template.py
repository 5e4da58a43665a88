"""Source template of the numba kernel (see ``compiled.py``): pure-Python code, as text.

The text is expanded (named offsets into the flat work and constants vectors) and compiled
by ``compiled.py``; it is a scalar, allocation-free transcription of the step defined in
``step.py`` (the φ-matrices of the plan, the linearly-implicit correction for g, the update
law's step with the box projection, the second observer, the divergence rule of
``step.DIVERGENCE_BOUND``); ``tests/estimation/test_conformance.py`` holds it to that
definition. Its data (matrices, gains, φ-matrices, Γ, Θ) come from the observer's StepPlan and
its g, Jacobians and θ* are printed from the same SymPy expressions the Python path
lambdifies.
"""

#: The dimension-generic part of every kernel, in a notation that :func:`_expand` rewrites:
#: ``L[i, j]``, ``g[a]``, … name blocks of the constants vector P and the work vector w
#: (see :func:`_layouts`), and ``x[j]``, ``z[a]``, ``th[i]``, ``x2[j]`` the parts of the state
#: in row ``iin`` of ``Sin``. The upper-case names are module constants written above it
#: (dimensions and offsets); ``flags`` holds the law code (0 ConstantLaw, 1 AlgebraicInversion,
#: 2 IntermittentInversion, 3 GradientInversion), on_invalid == 'freeze', whether a second
#: observer is attached and its g_on_estimates — data, so that one kernel serves them all;
#: ``_g``, ``_g_dx``, ``_dg_dtheta``, ``_dg_dv`` and ``_theta_star`` are the generated model
#: functions.
CORE = '''

@njit(cache=True, error_model='numpy')
def _solve(q, w, o_M, o_b):
    # Gaussian elimination with partial pivoting of the q×q matrix stored row-major at
    # w[o_M:]; the right-hand side at w[o_b:] is overwritten by the solution
    for c in range(q):
        piv = c
        best = abs(w[o_M + c * q + c])
        for i in range(c + 1, q):
            if abs(w[o_M + i * q + c]) > best:
                best = abs(w[o_M + i * q + c])
                piv = i
        if piv != c:
            for j in range(q):
                tmp = w[o_M + c * q + j]
                w[o_M + c * q + j] = w[o_M + piv * q + j]
                w[o_M + piv * q + j] = tmp
            tmp = w[o_b + c]
            w[o_b + c] = w[o_b + piv]
            w[o_b + piv] = tmp
        for i in range(c + 1, q):
            f = w[o_M + i * q + c] / w[o_M + c * q + c]
            for j in range(c + 1, q):
                w[o_M + i * q + j] -= f * w[o_M + c * q + j]
            w[o_b + i] -= f * w[o_b + c]
    for c in range(q - 1, -1, -1):
        acc = w[o_b + c]
        for j in range(c + 1, q):
            acc -= w[o_M + c * q + j] * w[o_b + j]
        w[o_b + c] = acc / w[o_M + c * q + c]


@njit(cache=True, error_model='numpy')
def _implicit_step(q, P, o_Phi, w, o_F, o_N, o_M, o_r, Sin, iin, Sout, iout, o_s):
    # discretize.linearly_implicit_exponential_step on the q states at o_s:
    # s+ = s + (I - IMPLICITNESS Phi N)^-1 Phi F
    for i in range(q):
        acc = 0.0
        for j in range(q):
            acc += P[o_Phi + i * q + j] * w[o_F + j]
        w[o_r + i] = acc
        for j in range(q):
            acc = 0.0
            for l in range(q):
                acc += P[o_Phi + i * q + l] * w[o_N + l * q + j]
            w[o_M + i * q + j] = acc * -IMPLICITNESS
        w[o_M + i * q + i] += 1.0
    _solve(q, w, o_M, o_r)
    for i in range(q):
        Sout[iout, o_s + i] = Sin[iin, o_s + i] + w[o_r + i]


@njit(cache=True, error_model='numpy')
def _expm(q, w, o_Z, o_E, o_T, o_U):
    # exp(Z) into E: Taylor series of degree 20 after scaling ||Z||_1 below 1/2, then squaring
    nrm = 0.0
    for j in range(q):
        acc = 0.0
        for i in range(q):
            acc += abs(w[o_Z + i * q + j])
        nrm = max(nrm, acc)
    squarings = 0
    scale = 1.0
    while nrm * scale > 0.5 and squarings < 1100:
        scale *= 0.5
        squarings += 1
    for i in range(q):
        for j in range(q):
            w[o_T + i * q + j] = 1.0 if i == j else 0.0
            w[o_E + i * q + j] = w[o_T + i * q + j]
    for deg in range(1, 21):
        for i in range(q):
            for j in range(q):
                acc = 0.0
                for l in range(q):
                    acc += w[o_T + i * q + l] * w[o_Z + l * q + j]
                w[o_U + i * q + j] = acc * scale / deg
        for i in range(q * q):
            w[o_T + i] = w[o_U + i]
            w[o_E + i] += w[o_U + i]
    for _ in range(squarings):
        for i in range(q):
            for j in range(q):
                acc = 0.0
                for l in range(q):
                    acc += w[o_E + i * q + l] * w[o_E + l * q + j]
                w[o_U + i * q + j] = acc
        for i in range(q * q):
            w[o_E + i] = w[o_U + i]


@njit(cache=True, error_model='numpy')
def _into_box(c, fallback, lo, hi):
    # law_base.finite_candidate followed by the projection onto the box (a clip)
    if c != c:
        c = fallback
    c = min(max(c, -FAR), FAR)
    return min(max(c, lo), hi)


@njit(cache=True, error_model='numpy')
def _law_step(Sin, iin, dt, P, w):
    # θ̂ after the step into thn; reads v, φ̂, g (and ∂g/∂θ for law 3) written by _advance
    law = int(flags[0])
    if law == 0:
        for i in range(NP):
            thn[i] = min(max(th[i], lower[i]), upper[i])
        return 0
    if law == 3:
        for a in range(NK):
            resid[a] = phi[a] - g[a]
        for a in range(NP):
            for b in range(NK):
                acc = 0.0
                for c in range(NP):
                    acc += Gam[a, c] * Gth[b, c]
                GM[a, b] = acc
        for a in range(NP):
            acc = 0.0
            for b in range(NK):
                acc += GM[a, b] * resid[b]
            fvec[a] = acc
            for c in range(NP):
                acc = 0.0
                for b in range(NK):
                    acc += GM[a, b] * Gth[b, c]
                Kmat[a, c] = acc
        ok = True
        for a in range(NP + 1):
            for c in range(NP + 1):
                Zm[a, c] = 0.0
        for a in range(NP):
            for c in range(NP):
                Zm[a, c] = -dt * Kmat[a, c]
                ok = ok and math.isfinite(Zm[a, c])
            Zm[a, NP] = dt * fvec[a]
            ok = ok and math.isfinite(Zm[a, NP])
        if not ok:
            for a in range(NP + 1):
                for c in range(NP + 1):
                    Zm[a, c] = 0.0
        _expm(NP + 1, w, W_Zm, W_Ex, W_T1, W_T2)
        for a in range(NP):
            ok = ok and math.isfinite(Ex[a, NP])
        for a in range(NP):
            if ok:
                delta = Ex[a, NP]
            elif math.isfinite(fvec[a]):
                delta = dt * fvec[a]
            elif fvec[a] > 0:
                delta = FAR
            elif fvec[a] < 0:
                delta = -FAR
            else:
                delta = 0.0
            thn[a] = _into_box(th[a] + delta, th[a], lower[a], upper[a])
        return 0
    lw = 1.0
    if law == 2:
        big = 0.0
        for a in range(NK):
            big = max(big, abs(phi[a]))
        safe = big if big > 0 else 1.0
        acc = 0.0
        for a in range(NK):
            acc += (phi[a] / safe) ** 2
        tt = (big * math.sqrt(acc) - ramp[0]) / (ramp[1] - ramp[0])
        tt = min(max(tt, 0.0), 1.0)
        lw = min(max(tt * tt * (3.0 - 2.0 * tt), 0.0), 1.0)
    _theta_star(w, Sin, iin, W_v, 0, W_phi, W_ts)
    if lw > 0:
        for i in range(NP):
            if not math.isfinite(ts[i]):
                if flags[1] == 0.0:
                    return 2
                lw = 0.0
    for i in range(NP):
        target = ts[i] if lw > 0 else th[i]
        decay = math.exp(-lw * dt * Gam[i, i])
        thn[i] = _into_box(target - decay * (target - th[i]), th[i], lower[i], upper[i])
    return 0


@njit(cache=True, error_model='numpy')
def _advance(Sin, iin, U, Y, iu, dt, P, w, Sout, iout):
    # one step of observer (3), law (8) and the second observer from row iin of Sin with the
    # samples in row iu of U and Y, into row iout of Sout; returns 0 or an error code
    law = int(flags[0])
    on_est = flags[3] != 0.0
    for i in range(NU):
        v[i] = U[iu, i]
    for i in range(NY):
        v[NU + i] = Y[iu, i]
    _g_dx(w, Sin, iin, W_v, 0, NZ, W_g, W_Gx)
    for i in range(NZ):
        a1 = 0.0
        for j in range(NZ):
            a1 += L[i, j] * Sin[iin, j]
        a2 = 0.0
        for j in range(NV):
            a2 += Bv[i, j] * v[j]
        F[i] = a1 + a2
    for i in range(NX):
        acc = 0.0
        for j in range(NK):
            acc += E[i, j] * g[j]
        F[i] += acc
    for i in range(NY):
        acc = 0.0
        for j in range(NX):
            acc += C[i, j] * x[j]
        innov[i] = v[NU + i] - acc
    for i in range(NX):
        acc = 0.0
        for j in range(NY):
            acc += Kx[i, j] * innov[j]
        kin[i] = acc
    for a in range(NK):
        acc = 0.0
        for j in range(NX):
            acc += Gx[a, j] * kin[j]
        F[NX + a] -= acc
        phi[a] = g[a] + z[a]
        if not math.isfinite(phi[a]):
            return 1
    if law == 3:
        _dg_dtheta(w, Sin, iin, W_v, 0, NZ, W_Gth)
    status = _law_step(Sin, iin, dt, P, w)
    if status != 0:
        return status
    moving = False
    for i in range(NP):
        dth[i] = thn[i] - th[i]
        if dth[i] != 0.0:
            moving = True
    if moving:
        if law != 3:
            _dg_dtheta(w, Sin, iin, W_v, 0, NZ, W_Gth)
        for a in range(NK):
            acc = 0.0
            for j in range(NP):
                acc += Gth[a, j] * dth[j]
            F[NX + a] += -acc / dt
    for i in range(NZ):
        for j in range(NZ):
            Nm[i, j] = 0.0
    for i in range(NX):
        for j in range(NX):
            acc = 0.0
            for a in range(NK):
                acc += E[i, a] * Gx[a, j]
            Nm[i, j] = acc
    for a in range(NK):
        for j in range(NX):
            acc = 0.0
            for l in range(NX):
                acc += Gx[a, l] * KxC[l, j]
            Nm[NX + a, j] = acc
    if flags[2] != 0.0:
        # the second observer first: it reads θ̂ at the start of the step, and Sout may be Sin
        for i in range(NY):
            acc = 0.0
            for j in range(NX):
                acc += C[i, j] * x2[j]
            yhat[i] = acc
            inn2[i] = v[NU + i] - acc
        for i in range(NU):
            v2[i] = v[i]
        for i in range(NY):
            v2[NU + i] = yhat[i] if on_est else v[NU + i]
        _g_dx(w, Sin, iin, W_v2, NZ + NP, NZ, W_g2, W_Gx2)
        if on_est:
            _dg_dv(w, Sin, iin, W_v2, NZ + NP, NZ, W_Gv2)
            for a in range(NK):
                for j in range(NX):
                    acc = 0.0
                    for i in range(NY):
                        acc += Gv2[a, NU + i] * C[i, j]
                    Gx2[a, j] += acc
        for i in range(NX):
            a1 = 0.0
            for j in range(NX):
                a1 += A[i, j] * x2[j]
            a2 = 0.0
            for j in range(NU):
                a2 += Bm[i, j] * v[j]
            a3 = 0.0
            for j in range(NK):
                a3 += E[i, j] * g2[j]
            a4 = 0.0
            for j in range(NY):
                a4 += K2[i, j] * inn2[j]
            F2[i] = ((a1 + a2) + a3) + a4
            for j in range(NX):
                acc = 0.0
                for a in range(NK):
                    acc += E[i, a] * Gx2[a, j]
                N2[i, j] = acc
        _implicit_step(NX, P, P_Phi12, w, W_F2, W_N2, W_M2, W_rhs2, Sin, iin, Sout, iout,
                       NZ + NP)
    _implicit_step(NZ, P, P_Phi1, w, W_F, W_Nm, W_M, W_rhs, Sin, iin, Sout, iout, 0)
    for i in range(NP):
        Sout[iout, NZ + i] = thn[i]
    return 0


@njit(cache=True, error_model='numpy')
def step(s, u, y, dt, P, out):
    w = np.zeros(W_SIZE)
    size = s.shape[0]
    return _advance(s.reshape((1, size)), 0, u.reshape((1, NU)), y.reshape((1, NY)), 0, dt,
                    P, w, out.reshape((1, size)), 0)


@njit(cache=True, error_model='numpy')
def run(s0, U, Y, dts, P, S, PHI):
    w = np.zeros(W_SIZE)
    N, size = S.shape
    for j in range(size):
        S[0, j] = s0[j]
    for i in range(N - 1):
        status = _advance(S, i, U, Y, i, dts[i], P, w, S, i + 1)
        for a in range(NK):
            PHI[i, a] = phi[a]
        if status != 0:
            return status, i
        sq = 0.0
        for j in range(size):
            sq += S[i + 1, j] * S[i + 1, j]
        if not sq <= BOUND_SQ:
            return 1, i
    for j in range(NU):
        v[j] = U[N - 1, j]
    for j in range(NY):
        v[NU + j] = Y[N - 1, j]
    _g(w, S, N - 1, W_v, 0, NZ, W_g)
    for a in range(NK):
        PHI[N - 1, a] = g[a] + S[N - 1, NX + a]
    return 0, 0
'''
