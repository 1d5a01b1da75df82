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


def test_a_swap_of_two_features_with_different_ranges_is_named():
    from twinfalsify.unitscreen import swapped

    # each within a factor 2 of the other's reference, so only the typical ranges see it
    assert against_reference("Sodium", 104.0, 140.0) == ""
    assert swapped({"Sodium": 104.0, "Chloride": 140.0, "HR": 90.0}) == [
        "Sodium and Chloride swapped? (twin median Sodium 104, typical 120-160; Chloride "
        "140, typical 85-125 mmol/L)"]
    # the right way round, or one of them alone off: no swap
    assert swapped({"Sodium": 140.0, "Chloride": 104.0}) == []
    assert swapped({"Sodium": 104.0, "Chloride": 104.0}) == []
    # different units are never a swap (SysBP 140 mmHg, Glucose 100 mg/dL)
    assert swapped({"SysBP": 100.0, "Glucose": 140.0}) == []


def test_outside_the_typical_range_where_the_reference_is_inside():
    from twinfalsify.unitscreen import outside_typical

    assert outside_typical("Sodium", 104.0, 140.0) == \
        "Sodium: twin median 104, data 140 mmol/L, outside the typical 120-160"
    assert outside_typical("Sodium", 141.0, 140.0) == ""
    # the reference itself atypical (a sick cohort, a table in another unit): not the twin's
    assert outside_typical("Sodium", 104.0, 110.0) == ""


def test_drift_after_hour_one_names_the_first_hour_outside():
    from twinfalsify.unitscreen import drifts

    assert drifts("HR", [90.0, 135.0, 180.0, 225.0]) == \
        "HR: twin median 90 at hour 1, 180 at hour 3 (typical 50-140 /min): drifts after hour 1?"
    assert drifts("HR", [90.0, 95.0, 100.0]) == ""
    assert drifts("HR", [127.0, 140.0, 156.0]) == ""  # runs high, moves little: no drift
    assert drifts("HR", [200.0, 210.0]) == ""  # already off at hour 1: the units row's case
