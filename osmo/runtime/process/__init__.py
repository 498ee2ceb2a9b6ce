"""The process runtime family: a task's command runs as host processes, sandboxed or not.

Modules: ``groups`` (commands as process groups: spawn, kill, reap, exit codes), ``sandbox``
(bubblewrap, the one module that knows its flags), ``netns`` and ``netns_keeper`` (the
node's namespaces that sandboxed tasks share), ``proctable`` (recognising a process across a
crash), ``ports`` (which ports a task listens on).
"""
