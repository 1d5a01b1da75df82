"""The fault-injecting twin with a child that keeps its stdout open.

    python tests/fakes/daemon_twin.py --pid-file FILE [--escape] [--child-seconds S] \
        [faulty_twin.py arguments ...]

Before answering anything it forks a child that inherits stdin, stdout and stderr and
sleeps ``--child-seconds`` (default 120), as an engine or a logging helper started by a
twin may do; the child's pid is appended to ``--pid-file`` so a test can check it was
killed (or kill it itself). ``--escape`` makes the child leave the twin's process group
(``setsid``, as a daemon does), out of reach of a group kill. The twin itself then runs
``faulty_twin.py`` with the remaining arguments (``--mode crash`` makes it exit while
the child holds its stdout).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

from faulty_twin import main as faulty_main


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pid-file", required=True)
    parser.add_argument("--escape", action="store_true")
    parser.add_argument("--child-seconds", type=float, default=120.0)
    args, rest = parser.parse_known_args(argv)
    sys.stdout.flush()
    pid = os.fork()
    if pid == 0:  # the child: hold the pipes, do nothing
        if args.escape:
            os.setsid()
        time.sleep(args.child_seconds)
        os._exit(0)
    with open(args.pid_file, "a") as fh:
        fh.write(f"{pid}\n")
    return faulty_main(rest)


if __name__ == "__main__":
    sys.exit(main())
