"""One engine: the Pulse Physiology Engine 4.2 served over the twin protocol (``worker``), its
unit conversions, clamp and physiological-limit tables (``units`` and ``data/``), and the
replay twin that serves recorded Pulse runs (``replay``).

May import: ``runs.protocol`` and ``schema``; nothing else of the library imports it.
"""
