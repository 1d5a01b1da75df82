"""What a twin is: the Twin interface (X_0 and a_1:t in, Xtwin_1:t and one status per run out)
and the builtin twins of the synthetic world (oracle, biased, fitted).

May import: ``schema``, ``noise`` and ``sources`` only; never ``runs`` or ``pulse``.
"""
