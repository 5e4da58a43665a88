"""The model of the paper, (1): ẋ = A x + B u + E φ, y = C x, φ = g(v, x, θ), θ ∈ Θ.

:mod:`.system` holds the plant (:class:`~thetahat.model.system.PerturbedLinearSystem`),
:mod:`.perturbation` the perturbation g with its Jacobians, :mod:`.paramset` and
:mod:`.set_geometry` the convex parameter sets Θ and their projections, :mod:`.state_set` the
box X of the states and g saturated outside it (Remark 1), :mod:`.parse` the
parser of perturbations given as text (never evaluated), :mod:`.lambdify` the one SymPy →
NumPy printer, :mod:`.jacobian_check` the checks of g's Jacobians and :mod:`.interop` the
adapters to python-control and scipy.signal.

What it may import: the package's helpers (errors, limits, validation) only; everything else
builds on it.
"""
