"""ObserverResult as a DataFrame / xarray Dataset, and plot_result on any model."""

import importlib.util

import numpy as np
import pytest

from thetahat.models import prop4_pe, two_inertia


@pytest.fixture(scope="module")
def result():
    tr = two_inertia.simulate(seed=0, t_end=0.2)
    return two_inertia.observer().run(tr.t, tr.u, tr.y)


def test_to_dataframe_holds_the_arrays(result):
    pytest.importorskip("pandas")
    df = result.to_dataframe(state_names=["omega_m", "twist", "omega_l"],
                             parameter_names=["F_m", "F_l"])
    assert df.index.name == "t" and len(df) == result.t.size
    np.testing.assert_array_equal(df["theta_hat_F_l"].to_numpy(), result.theta_hat[:, 1])
    np.testing.assert_array_equal(df["x_hat_twist"].to_numpy(), result.x_hat[:, 1])
    assert list(df.columns)[:3] == ["x_hat_omega_m", "x_hat_twist", "x_hat_omega_l"]


def test_to_xarray_holds_the_arrays(result):
    pytest.importorskip("xarray")
    ds = result.to_xarray(parameter_names=["F_m", "F_l"])
    np.testing.assert_array_equal(ds["theta_hat"].sel(parameter="F_m").values,
                                  result.theta_hat[:, 0])
    assert ds["phi_hat"].shape == result.phi_hat.shape


def test_plot_result_any_model(tmp_path):
    pytest.importorskip("matplotlib")
    from thetahat.plotting import plot_result

    sys_ = prop4_pe.system()
    from thetahat import ModifiedHighGainObserver, modified_high_gain
    d = modified_high_gain(sys_.A, sys_.E, sys_.C, 0.5)
    obs = ModifiedHighGainObserver.from_design(sys_, d, prop4_pe.update_law())
    t = np.arange(0.0, 2.0, 0.01)
    res = obs.run(t, prop4_pe.input_signal(t), np.zeros((t.size, 1)))
    fig = plot_result(res, sys_, tmp_path / "f.png", theta=prop4_pe.THETA)
    assert (tmp_path / "f.png").stat().st_size > 0
    assert len(fig.axes) == 1 + 1 + 2                   # r + k + p panels
    lo, hi = fig.axes[-1].get_ylim()
    assert lo <= -2.0 and hi >= 2.0                     # Θ's bounds are drawn


def test_the_tables_take_the_names_the_result_carries():
    """A model file's run carries its names: the columns and coordinates use them unasked;
    names given override them; a wrong count is refused."""
    from pathlib import Path

    from thetahat.errors import DimensionError
    from thetahat.modelfile import load_model, run_estimator, simulate_model
    from thetahat.tables import result_columns, result_names

    spec = load_model(Path(__file__).resolve().parents[1] / "examples" / "two_inertia.toml")
    data = simulate_model(spec, seed=0, t_end=0.2)
    res = run_estimator(spec, data.t, data.u, data.y, diagnose=False)
    cols = result_columns(res)
    for i, n in enumerate(spec.parameter_names):
        np.testing.assert_array_equal(cols[f"theta_hat_{n}"], res.theta_hat[:, i])
    for i, n in enumerate(spec.state_names):
        np.testing.assert_array_equal(cols[f"x_hat_{n}"], res.x_hat[:, i])
    assert result_names(res, parameter_names=["a", "b"]) == (list(spec.state_names), ["a", "b"])
    with pytest.raises(DimensionError, match="1 parameter names for 2 parameters"):
        result_columns(res, parameter_names=["a"])
    if importlib.util.find_spec("pandas") is not None:
        assert list(res.to_dataframe().columns) == list(cols)
    if importlib.util.find_spec("xarray") is not None:
        ds = res.to_xarray()
        assert list(ds["parameter"].values) == list(spec.parameter_names)
        assert list(ds["state"].values) == list(spec.state_names)
