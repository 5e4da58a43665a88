"""Issue 37 (hostile round 3): the streaming protocol validated at the boundary.

Every estimator's ``step`` and ``run`` check what they are handed with one helper
(:mod:`thetahat.estimation.protocol`: ``check_state``, ``check_sample``, ``check_step_length``;
:func:`thetahat.estimation.records.check_magnitude`): the state's type and its model's
dimensions, the samples' shapes, dt (a real number, finite, > 0), and magnitudes float64
arithmetic can take. A state is a *model's*: any estimator of the same model continues a value
state (the observers' vectors, the EKF's state), and stepping one twice gives the same next
state twice; a state that carries a stream (guarded, MAP) continues only with the estimator
that started the stream, once.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from thetahat import errors as E
from thetahat.estimation.statistical.ekf import JointEKF
from thetahat.estimation.statistical.guarded import GuardedEstimator
from thetahat.estimation.statistical.mle import MapEstimator
from thetahat.modelfile import build_observer, load_model
from thetahat.models import lugre

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SIGMA = 0.02
DT = 1e-3


def _compiled():
    pytest.importorskip("numba")
    from thetahat.estimation.observer.compiled import compile_observer
    return compile_observer(lugre.observer(), dt=DT)


def _native():
    from thetahat.codegen.loader import find_compiler
    from thetahat.codegen.native import NativeObserver
    if find_compiler() is None:
        pytest.skip("no C compiler")
    obs = lugre.observer()
    return NativeObserver(obs, lambda: obs)


FACTORIES = {
    "paper": lambda: lugre.observer(),
    "compiled": _compiled,
    "native": _native,
    "guarded": lambda: GuardedEstimator(stage1=lugre.observer(), system=lugre.system(),
                                        noise_std=SIGMA, use_fits=False, compiled=False),
    "mle": lambda: MapEstimator(system=lugre.system(), noise_std=SIGMA, compiled=False),
    "ekf": lambda: JointEKF(system=lugre.system(), noise_std=SIGMA, compiled=False),
}
#: Estimators whose state carries a stream shared by its states.
STREAMS = ("guarded", "mle")


def other_model_state(name):
    """A state of the same kind for another model (two_inertia: n = 3, p = 2)."""
    spec = load_model(EXAMPLES / "two_inertia.toml")
    if name in ("paper", "compiled", "native"):
        return build_observer(spec).init()
    cls = {"guarded": lambda: GuardedEstimator(stage1=build_observer(spec), system=spec.system,
                                               compiled=False),
           "mle": lambda: MapEstimator(system=spec.system, compiled=False),
           "ekf": lambda: JointEKF(system=spec.system, compiled=False)}[name]
    return cls().init()


@pytest.fixture(scope="module", params=list(FACTORIES))
def est(request):
    return request.param, FACTORIES[request.param]()


@pytest.fixture(scope="module")
def data():
    return lugre.simulate(seed=1, t_end=0.05)


def _theta(name, est, state):
    if name in ("paper", "compiled", "native"):
        obs = est if name == "paper" else est.observer
        return np.asarray(state)[obs.layout.theta]
    return np.asarray(state.theta_hat)


# --- the state -------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", ["None", "text", "another estimator's", "another model's"])
def test_a_state_it_cannot_continue_is_refused(est, bad):
    name, e = est
    other = (JointEKF if name != "ekf" else MapEstimator)(system=lugre.system(),
                                                           compiled=False).init()
    state = {"None": None, "text": "state", "another estimator's": other,
             "another model's": other_model_state(name)}[bad]
    calls = [lambda: e.step(state, [0.1], [0.1], DT)]
    if state is not None:                         # run(state0=None) starts from init()
        calls.append(lambda: e.run(np.arange(20) * DT, np.zeros(20), np.zeros(20),
                                   state0=state))
    for call in calls:
        with pytest.raises(E.StateError, match=r"init\(\)"):
            call()


def test_a_value_state_may_be_stepped_twice_and_by_another_instance(est):
    """Observers and the EKF: the state is a value (documented on their ``step``)."""
    name, e = est
    if name in STREAMS:
        pytest.skip("a stream's state: see the next test")
    s1 = e.step(e.init(theta_hat0=[0.5]), [0.1], [0.1], DT)
    a, b = e.step(s1, [0.2], [0.3], DT), e.step(s1, [0.2], [0.3], DT)
    twin = FACTORIES[name]()
    c = twin.step(s1, [0.2], [0.3], DT)
    for other in (b, c):
        np.testing.assert_array_equal(_theta(name, e, a), _theta(name, e, other))


def test_a_stream_state_is_stepped_once_by_its_own_estimator(est):
    """Guarded and MAP: a stepped state again, or by another estimator, is refused; a fresh
    ``init()`` state starts a stream of whichever estimator steps it."""
    name, e = est
    if name not in STREAMS:
        pytest.skip("a value state: see the previous test")
    s0 = e.init(theta_hat0=[0.5])
    s1 = e.step(s0, [0.1], [0.1], DT)
    s2 = e.step(s1, [0.2], [0.3], DT)
    with pytest.raises(E.StateError, match="stepped already"):
        e.step(s1, [0.2], [0.3], DT)
    twin = FACTORIES[name]()
    with pytest.raises(E.StateError, match="started by another"):
        twin.step(s2, [0.2], [0.3], DT)
    fresh = twin.step(s0, [0.1], [0.1], DT)          # init() states: anyone's
    np.testing.assert_array_equal(fresh.theta_hat, s1.theta_hat)
    e.step(s2, [0.2], [0.3], DT)                     # the latest goes on


# --- the samples and dt ----------------------------------------------------------------------

@pytest.mark.parametrize("u,y,words", [
    ([0.1, 0.2], [0.1], "u must have length 1"), ([0.1], [0.1, 0.2], "y must have length 1"),
    ([0.1], [[0.1]], "y must be a 1-D vector"), ("a", [0.1], "u must be"),
    ([0.1], None, "y must be"),
    ([np.nan], [0.1], "u contains NaN"), ([0.1], [np.inf], "y contains inf"),
])
def test_samples_of_the_wrong_shape_or_kind_are_refused(est, u, y, words):
    name, e = est
    s = e.init()
    with pytest.raises((E.DimensionError, E.NonFiniteError), match=words):
        e.step(s, u, y, DT)


@pytest.mark.parametrize("dt,error", [(0.0, E.DimensionError), (-1e-3, E.DimensionError),
                                      (np.nan, E.NonFiniteError), (np.inf, E.NonFiniteError),
                                      ("1e-3x", E.DimensionError), (None, E.DimensionError),
                                      (1e300, E.InputLimitError), (1e-300, E.InputLimitError)])
def test_dt_is_a_finite_positive_number_of_a_sane_magnitude(est, dt, error):
    name, e = est
    with pytest.raises(error, match="dt"):
        e.step(e.init(), [0.1], [0.1], dt)


@pytest.mark.parametrize("u,y", [([1e300], [0.1]), ([0.1], [1e300]), ([1e-300], [0.1]),
                                 ([0.1], [-3e-200])])
def test_a_sample_beyond_float64_s_reach_names_the_scale(est, u, y):
    name, e = est
    with pytest.raises(E.InputLimitError, match=r"magnitude .*Rescale"):
        e.step(e.init(), u, y, DT)


def test_zero_samples_are_fine(est):
    name, e = est
    e.step(e.init(), [0.0], [0.0], DT)


# --- records ---------------------------------------------------------------------------------

SCALINGS = {"t·1e300": lambda t, u, y: (t * 1e300, u, y),
            "t·1e-300": lambda t, u, y: (t * 1e-300, u, y),
            "u·1e300": lambda t, u, y: (t, u * 1e300, y),
            "y·1e-300": lambda t, u, y: (t, u, y * 1e-300),
            "y·1e300": lambda t, u, y: (t, u, y * 1e300)}


@pytest.mark.parametrize("scaling", SCALINGS.values(), ids=SCALINGS.keys())
def test_a_record_beyond_float64_s_reach_names_the_scale(est, data, scaling):
    """The issue's ``run(t·1e300)`` ('math domain error') and ``MapEstimator.run(y·1e-300)``
    (LinAlgError): refused before any arithmetic, naming the value, the bound and the fix."""
    name, e = est
    t, u, y = scaling(data.t, data.u, data.y)
    for throw in (True, False):
        with pytest.raises(E.InputLimitError, match=r"magnitude .*Rescale .* unit"):
            e.run(t, u, y, throw=throw)


@pytest.mark.parametrize("model", ["prop3", "two_inertia", "heater", "spring_friction"])
@pytest.mark.parametrize("method", ["paper", "ekf"])
def test_magnitudes_are_checked_for_every_model(model, method):
    """The same bounds whatever the model (three shipped models besides LuGre), and a record
    at the bounds' edge of the model's own scale is still accepted."""
    from thetahat.modelfile.study import simulate_model
    spec = load_model(EXAMPLES / f"{model}.toml")
    run = simulate_model(spec, 0, t_end=0.5)
    e = (build_observer(spec) if method == "paper"
         else JointEKF(system=spec.system, noise_std=0.01, compiled=False))
    with pytest.raises(E.InputLimitError, match="y: a value of magnitude"):
        e.run(run.t, run.u, run.y * 1e-200)
    with pytest.raises(E.InputLimitError, match="t: a value of magnitude"):
        e.run(run.t * 1e200, run.u, run.y)
    res = e.run(run.t, run.u, run.y, throw=False)          # the model's own scale: fine
    assert res.t.shape == run.t.shape


def test_one_helper_checks_every_estimator():
    """No estimator carries checks of its own: every ``step`` goes through the protocol's
    helpers or delegates to a ``step`` that does (read from the sources, so that a new
    estimator is caught too)."""
    import inspect

    from thetahat.codegen.native import NativeObserver
    from thetahat.estimation.observer.compiled import CompiledObserver
    from thetahat.estimation.observer.observer import ModifiedHighGainObserver
    for cls in (ModifiedHighGainObserver, CompiledObserver, GuardedEstimator, MapEstimator,
                JointEKF, NativeObserver):
        src = inspect.getsource(cls.step)
        helpers = ("check_step_length", "stream_sample", "self.observer.step(")
        assert any(h in src for h in helpers), cls.__name__
        assert "positive_scalar" not in src and "float(dt)" not in src, cls.__name__


def test_state_error_is_a_dimension_error():
    """Callers that caught the earlier DimensionError keep working."""
    assert issubclass(E.StateError, E.DimensionError) and issubclass(E.StateError, ValueError)
    assert dataclasses.is_dataclass(MapEstimator)


# ---- the fast path of a stream's checks accepts exactly what the full checks accept -------
# (a float64 vector of the model's size takes the fast path; the same values as a list take
# the full checks: equal copies out, or the same error, for every kind of value)
_VALUES = [0.0, -0.0, 1.0, -2.5e3, 1e-150, 1e150, -1e150 * (1 + 1e-15), 9.9e-151, 5e-324,
           2e150, np.inf, -np.inf, np.nan, 1e-300, 3.0]


def _outcome(fn):
    try:
        return "ok", [np.asarray(a).tobytes() for a in fn()]
    except E.ThetahatError as exc:
        return type(exc).__name__, str(exc)


@pytest.mark.parametrize("name", ["lugre.toml", "two_inertia.toml", "heater.toml",
                                  "spring_friction.toml"])
def test_a_stream_sample_s_fast_check_accepts_what_the_full_check_accepts(name):
    from thetahat.estimation.protocol import check_sample, check_state, check_step_length
    sys_ = build_observer(load_model(EXAMPLES / name)).system
    rng = np.random.default_rng(7)
    kinds = {"ok": 0, "refused": 0}
    for _ in range(300):
        u = rng.choice(_VALUES, sys_.m).astype(np.float64)
        y = rng.choice(_VALUES, sys_.r).astype(np.float64)
        if rng.random() < 0.5:                      # plain values most of the time too
            u, y = rng.normal(size=sys_.m), rng.normal(size=sys_.r)
        fast = _outcome(lambda: check_sample(sys_, u, y))
        full = _outcome(lambda: check_sample(sys_, u.tolist(), y.tolist()))
        assert fast == full, (u, y)
        kinds["ok" if fast[0] == "ok" else "refused"] += 1
    assert min(kinds.values()) > 20                 # both branches were compared
    for dt in _VALUES + [1e-3, -1e-3]:
        assert (_outcome(lambda: [check_step_length(float(dt))])
                == _outcome(lambda: [check_step_length(np.array(dt))])), dt
    s = rng.normal(size=7)
    assert check_state("obs.step", s, None, {"state": (7,)}) is s   # the array itself
    assert (check_state("obs.step", s.tolist(), None, {"state": (7,)}).tobytes()
            == s.tobytes())
    with pytest.raises(E.StateError):
        check_state("obs.step", s[:6], None, {"state": (7,)})

