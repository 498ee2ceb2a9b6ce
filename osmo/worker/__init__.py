"""Workers: what runs attempts, on the server's host (the local pool) or on a remote worker.

Modules: ``pool`` (the local pool of host processes, an ``osmo.executor.Executor``),
``endings`` (how its attempts end), ``remote`` (``osmo worker``), ``options`` (its flags),
``workdir`` and ``transfer`` (an attempt's folder, inputs and outputs), ``launch`` (typed
tasks), ``logs`` (the log format, its writer and cap), ``logread`` (reading a log by
position), ``masking``, ``secrets``, ``checkpoints``, ``reactor``, ``live``, ``machine``.
Nothing is imported here: ``osmo worker --help`` stays fast.
"""
