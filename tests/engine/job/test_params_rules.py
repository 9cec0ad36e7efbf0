"""Parameter rules in one place (``engine.params``): values a stage cannot take are refused when the parameters are
made, with a message naming the field, never deep inside a stage as an internal error."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.errors import InputError
from engine.params import (
    MIN_TRIANGLES,
    DecimateParams,
    ExportParams,
    IslandParams,
    PreprocessParams,
    ReconParams,
    SmoothParams,
    check_reduction,
    is_reduction,
    spacing_order_warning,
    target_faces,
)


@pytest.mark.parametrize("value", [0.2, 1, 1.0, 1e-6, np.float32(0.5), np.float64(0.25)])
def test_a_reduction_is_a_real_number_in_the_open_closed_unit_interval(value):
    assert is_reduction(value)
    assert check_reduction(value) == float(value)


@pytest.mark.parametrize("value", [0, 0.0, -0.1, 1.5, float("nan"), float("inf"), True, "0.2", None])
def test_anything_else_is_not_a_reduction(value):
    assert not is_reduction(value)
    with pytest.raises(ValueError, match=r"reduction must be in \(0, 1\]"):
        check_reduction(value)


@pytest.mark.parametrize("value", [0, 1.5, float("nan"), True])
def test_one_rule_for_reduction_in_every_layer(value):
    """The parameters, the numpy entry point's target and the paper's sweep refuse the same values."""
    from engine.paper.sweep import SweepConfig

    with pytest.raises(ValueError, match="reduction"):
        DecimateParams(reduction=value)
    with pytest.raises(ValueError, match="reduction"):
        target_faces(1000, value, None)
    with pytest.raises(ValueError, match="reduction"):
        SweepConfig(reductions=(0.2, value))


def test_max_triangles_with_the_default_reduction_is_refused_when_made():
    """``DecimateParams(max_triangles=1000)`` keeps the default reduction too: both targets at once were accepted and
    failed inside the decimate stage as an internal error; now the parameters refuse them, saying how to ask."""
    with pytest.raises(ValueError, match=r"not both .*reduction=None"):
        DecimateParams(max_triangles=1000)
    with pytest.raises(ValueError, match="not both"):
        ReconParams.from_dict({"decimate": {"max_triangles": 1000}})
    ok = DecimateParams(reduction=None, max_triangles=1000)
    assert ok.target_faces(50_000) == 1000
    assert ReconParams.from_dict({"decimate": {"reduction": None, "max_triangles": 1000}}).decimate == ok


def test_neither_target_is_refused():
    with pytest.raises(ValueError, match="give reduction or max_triangles"):
        DecimateParams(reduction=None)


@pytest.mark.parametrize("value", [MIN_TRIANGLES - 1, 0, -5, 1000.5, 1000.0, True, 2**31])
def test_max_triangles_is_an_integer_from_a_tetrahedron_up(value):
    with pytest.raises(ValueError, match="max_triangles must be an integer"):
        DecimateParams(reduction=None, max_triangles=value)


def test_target_faces_of_the_parameters_and_of_the_numpy_entry_point_agree():
    params = DecimateParams(reduction=0.3)
    for n in (1, 3, 10, 1001, 123_457):
        assert params.target_faces(n) == target_faces(n, 0.3, None) == max(round(0.3 * n), 1)
    assert target_faces(100, None, 1) == 1  # the numpy entry point takes any count from one face
    with pytest.raises(ValueError, match="exactly one"):
        target_faces(100, 0.5, 10)
    with pytest.raises(ValueError, match="exactly one"):
        target_faces(100, None, None)


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: SmoothParams(iterations=1.5), "iterations"),
        (lambda: SmoothParams(iterations=True), "iterations"),
        (lambda: SmoothParams(iterations=0), "iterations"),
        (lambda: IslandParams(keep_largest=2.5), "keep_largest"),
        (lambda: IslandParams(keep_largest=0), "keep_largest"),
        (lambda: PreprocessParams(area_opening_px=3.5), "area_opening_px"),
        (lambda: ExportParams(phone_max_triangles=5000.5), "phone_max_triangles"),
        (lambda: ExportParams(ar_max_triangles=99), "ar_max_triangles"),
    ],
)
def test_counts_are_integers_in_range(make, field):
    """Counts the stages loop over or size arrays by: a float or a bool failed inside a stage before."""
    with pytest.raises(ValueError, match=f"{field} must be an integer"):
        make()


def test_integers_of_numpy_types_are_counts_too():
    assert SmoothParams(iterations=np.int64(3)).iterations == 3
    assert DecimateParams(reduction=None, max_triangles=np.int32(500)).target_faces(10_000) == 500


def test_the_defaults_and_their_json_round_trip_still_pass_the_rules():
    p = ReconParams()
    assert ReconParams.from_dict(p.to_dict()) == p
    assert dataclasses.replace(p, decimate=DecimateParams(reduction=None, max_triangles=4)).decimate is not None


def test_the_cli_turns_a_refused_value_into_an_input_error():
    import argparse

    from engine.cli.args import recon_params

    args = argparse.Namespace(
        reduction=None, max_triangles=2, keep_specks=False, min_island_mm3=None, keep_largest=None, threshold=None,
        canny_sigma=None, area_opening_px=None, iso=1.0, preset=None, hu_offset=None, open=False, iterations=1,
        angle=0.5, first_slice="superior", flip_lr=False, flip_ap=False, keep_outside_body=True, outline_hu=-500.0,
    )  # fmt: skip
    with pytest.raises(InputError, match="max_triangles"):
        recon_params(args)


# ---- voxel size order: (z, y, x) everywhere, a swapped-looking one warned about ------------------------------------
@pytest.mark.parametrize(
    ("given", "likely"),
    [
        ((0.957, 0.957, 1.5), [1.5, 0.957, 0.957]),  # x, y, z from a README, read as z, y, x
        ((0.5, 0.6, 0.5), [0.6, 0.5, 0.5]),  # the odd one in y
        ((0.488, 0.4882812, 4.0), [4.0, 0.488, 0.488]),  # equal within 1 %
    ],
)
def test_a_voxel_size_that_looks_swapped_is_warned_with_the_likely_one(given, likely):
    warning = spacing_order_warning(given)
    assert warning is not None and warning["code"] == "voxel_size_order" and "looks swapped" in warning["message"]
    assert warning["likely_zyx_mm"] == likely and warning["given_zyx_mm"] == list(given)


@pytest.mark.parametrize("given", [(1.5, 0.957, 0.957), (0.5, 0.9, 0.9), (0.0041,) * 3, (5.0, 1.663, 1.66)])
def test_a_plausible_voxel_size_is_not_warned(given):
    assert spacing_order_warning(given) is None


def test_unequal_pixels_are_questioned_and_non_sizes_left_to_the_check():
    warning = spacing_order_warning((2.0, 1.0, 0.5))
    assert warning is not None and warning["likely_zyx_mm"] is None and "unequal in-plane" in warning["message"]
    assert spacing_order_warning((2.0, 1.0, 1.05)) is None  # within 10 %: rounding, not a swap
    assert spacing_order_warning((1.0, 1.0)) is None and spacing_order_warning("abc") is None
