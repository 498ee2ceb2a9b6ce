"""Workers: what runs attempts, on the server's host (the local pool) or on a remote worker.

How an attempt runs (a process, sandboxed or not, or a container) is ``osmo.runtime``'s;
everything around the run is here. Modules: ``pool`` (the local pool, an
``osmo.executor.Executor``, made of ``preparing``, ``starts`` and ``endings``, sharing
``live``'s table), ``remote`` (``osmo worker``), ``options`` (its flags), ``workdir`` and
``transfer`` (an attempt's folder, inputs and outputs), ``launch`` (typed tasks), ``logs``
(the log format, its writer and cap), ``logread`` (reading a log by position), ``sessions``
and ``exec_process`` (exec and port-forward), ``masking``, ``secrets``, ``checkpoints``,
``reactor``, ``machine``, ``procs``, ``held_inputs``, ``store_keeper``, ``taskenv``.
Nothing is imported here: ``osmo worker --help`` stays fast.
"""
