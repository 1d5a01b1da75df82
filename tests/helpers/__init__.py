"""What several test files share, one module per subject; test files import from here and
never from one another (pytest fixtures that several files use live in ``tests/conftest.py``).

- ``paths``: the checkout's folders, the shared data folder, the PYTHONPATH for subprocesses;
- ``workflow``: Snakemake studies run from the tests, folders built once per test run;
- ``studies``: a synthetic study run in-process (no Snakemake) and its twin samples;
- ``twins``: inputs and expected outputs for twin runs, a twin served in-process;
- ``docs``: the documentation site built in strict mode;
- ``reference``: earlier forms of optimised library code, which the fast forms must equal.
"""
