"""The ``osmo`` command line.

``main`` builds the parser, ``commands`` and one module per group of verbs run them,
``render`` prints (the only module importing ``rich``). Workflow verbs talk to a server
through the SDK; ``osmo server`` and ``osmo worker`` run one.
"""
