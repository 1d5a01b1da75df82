"""How twin runs are executed: the JSON-Lines twin protocol, the worker pool and runner, the
ProtocolTwin adapter, serving a builtin twin over the protocol, the registry that turns a
config's twin spec into a runnable twin, the prefix-tree run plan and the adaptive batch loop.

May import: ``twins`` and everything below it (``schema``, ``io``, ``noise``, ``sources``,
``design``, ``bounds``, ``inference``, ``falsify``); never ``pulse`` or the output modules.
"""
