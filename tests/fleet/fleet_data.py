"""A generated fleet: records of the Proposition 3 oscillator, each with its own θ."""

from pathlib import Path

import numpy as np
from thetahat.models import prop3_monotone as p3

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
MODEL = EXAMPLES / "prop3.toml"
#: 52 records (≥ 50, the issue's fleet), 10 s at 20 Hz: short, but θ̂ settles in ~3 s (Γ = 2).
N_FILES = 52
T_END, FS = 10.0, 20.0
CORRUPT = "m07.csv"
#: Noise on y: a position sensor with 0.1 % of the output range.
NOISE = 0.002


def true_theta(i: int) -> float:
    """θ of motor i, spread over Θ = [-2, 2] away from its edges."""
    return -1.6 + 3.2 * (i % 13) / 12


def write_fleet(directory: Path, n_files: int = N_FILES, *, corrupt: str | None = CORRUPT,
                parquet_every: int = 0) -> list[Path]:
    """Write the fleet (CSV; every ``parquet_every``-th as Parquet) and one corrupt file."""
    paths = []
    base = p3.simulate(seed=0, t_end=T_END, fs=FS, noise_std=0.0)
    for i in range(n_files):
        tr = p3.simulate(seed=i, theta=[true_theta(i)], t_end=T_END, fs=FS, noise_std=NOISE)
        table = np.c_[tr.t, tr.u, tr.y]
        if parquet_every and i % parquet_every == 1:
            import pyarrow as pa
            import pyarrow.parquet as pq
            path = directory / f"m{i:02d}.parquet"
            pq.write_table(pa.table({"t": table[:, 0], "u": table[:, 1], "y": table[:, 2]}),
                           path)
        else:
            path = directory / f"m{i:02d}.csv"
            np.savetxt(path, table, delimiter=",", header="t,u,y", comments="", fmt="%.17g")
        paths.append(path)
    if corrupt is not None:
        lines = (directory / corrupt).read_text().splitlines()
        lines[5] = lines[5].split(",")[0] + ",0.1,not-a-number"
        (directory / corrupt).write_text("\n".join(lines) + "\n")
    assert base.t.size == int(T_END * FS) + 1
    return paths
