"""``io.run_rule`` and ``io.cli_main`` end their process with its heap frozen
(``io.freeze_heap``), so that Python's last garbage collection at exit does not walk pandas',
matplotlib's and numba's objects; what reference counting frees is still freed."""

from __future__ import annotations

import gc
import weakref
from types import SimpleNamespace

import pytest

from twinfalsify.io import cli_main, freeze_heap, run_rule
from twinfalsify.schema import ContractError


def _raise(exc: Exception):
    def body(_sm):
        raise exc
    return body


@pytest.mark.parametrize("body", [lambda _sm: None, _raise(ContractError("bad input")),
                                  _raise(RuntimeError("a bug"))],
                         ids=["success", "bad input", "bug"])
def test_run_rule_freezes_the_heap_however_the_job_ends(tmp_path, body):
    gc.unfreeze()
    sm = SimpleNamespace(log=[str(tmp_path / "rule.log")], rule="split")
    try:
        try:
            run_rule(sm, body)
        except SystemExit as exc:
            assert exc.code == 1
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


@pytest.mark.parametrize(("body", "code"), [(lambda _: 0, 0), (lambda _: 3, 3),
                                            (_raise(ContractError("bad input")), 2)],
                         ids=["success", "exit code", "bad input"])
def test_a_command_lines_main_freezes_the_heap_however_it_ends(body, code, capsys):
    gc.unfreeze()
    try:
        assert cli_main(lambda: body(None), "prog") == code
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


def test_a_frozen_object_is_still_freed_when_its_last_reference_goes():
    class Thing:
        pass

    thing = Thing()
    gone = weakref.ref(thing)
    try:
        freeze_heap()
        assert gc.get_freeze_count() > 0
        del thing
        assert gone() is None  # reference counting, not the collector
    finally:
        gc.unfreeze()
