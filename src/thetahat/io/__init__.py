"""Reading logged records and writing estimates: CSV, Parquet, MATLAB, and the ``[data]`` mapping.

One reader path for every format: :func:`~thetahat.io.datafile.read_data` opens the file
(:mod:`.tables`: its columns, each cell checked for what it holds; :mod:`.matfile` for MATLAB's
headers), picks t, u and y (:mod:`.mapping`: the model's names or its ``[data]`` table), then
scales and checks the record once (finite, t increasing). :mod:`.record` holds the record read,
:mod:`.datafile` also the estimate writers.

What it may import: the package's helpers (errors, limits, safe_io) and
:mod:`thetahat.estimation.protocol` and :mod:`thetahat.estimation.records` (the result type a
writer writes, the NaN policies). A reader takes a :class:`~thetahat.io.mapping.RecordLayout`
(names, k, the ``[data]`` mapping; a model spec builds one as ``spec.layout``), never a model
spec: nothing here imports the model files, the specs, the CLI or an estimator.
"""
