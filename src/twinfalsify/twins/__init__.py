"""Digital twins: anything that, given X_0 and a_1:t, returns Xtwin_1:t."""
