"""The unit screen names the unit a feature's values look like (twin check, table check)."""

from __future__ import annotations

import pytest

from twinfalsify.unitscreen import TYPICAL, against_reference, against_typical


@pytest.mark.parametrize(("feature", "value", "reference", "unit"), [
    ("Glucose", 6.1, 128.0, "mmol/L"),   # 128 mg/dL = 7.1 mmol/L: within the 1.3 factor
    ("Calcium", 2.1, 8.6, "mmol/L"),
    ("Temp_C", 98.4, 36.9, "degF"),
    ("Temp_C", 310.0, 37.0, "K"),
    ("paO2", 12.5, 95.0, "kPa"),
    ("weight", 176.0, 80.0, "lb"),
    ("HR", 1.5, 88.0, "/s"),
])
def test_a_known_slip_is_named_with_its_unit(feature, value, reference, unit):
    message = against_reference(feature, value, reference)
    assert message.endswith(f": {unit}?"), message


def test_the_message_reads_as_the_author_needs_it():
    assert against_reference("Glucose", 6.1, 128.0) == \
        "Glucose: twin median 6.1, data 128 mg/dL: mmol/L?"


def test_close_medians_and_unknown_ratios():
    assert against_reference("Glucose", 140.0, 128.0) == ""
    assert against_reference("HR", 60.0, 100.0) == ""  # a factor < 2 is physiology, not unit
    far = against_reference("Sodium", 20.0, 140.0)
    assert far.startswith("Sodium: twin median 20, data 140 mmol/L: ratio 0.143")
    assert against_reference("Glucose", 5.0, 0.0) == ""  # no reference to compare with


def test_typical_ranges_name_the_unit_that_brings_a_median_back():
    assert against_typical("Glucose", 7.2) == \
        "Glucose: data median 7.2, typical 60-350 mg/dL: mmol/L?"
    assert against_typical("Temp_C", 98.6).endswith(": degF?")
    assert against_typical("Sodium", 20.0) == "Sodium: data median 20, typical 120-160 mmol/L"
    for feature, (lo, hi) in TYPICAL.items():
        assert against_typical(feature, (lo + hi) / 2) == ""
