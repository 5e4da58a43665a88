"""Reading logged records and writing estimates: CSV, Parquet, MATLAB, and the ``[data]`` mapping.

* :mod:`.datafile` — :func:`~thetahat.io.datafile.read_data` (t, u, y from a CSV, Parquet or
  MATLAB file) and the estimate writers;
* :mod:`.mapping` — the ``[data]`` table: which columns or variables are t, u and y, in what
  units;
* :mod:`.matfile` — the variables of a ``.mat`` file.

What it may import: the package's helpers (errors, limits, safe_io) and
:mod:`thetahat.estimation.protocol` (the result type a writer writes). A reader takes a
:class:`~thetahat.io.mapping.DataMapping` and the record's dimensions, never a model spec.
"""
