"""The time estimate `matspray run` prints before it starts: the work it counts, and what it says."""

import pytest

from matspray.method.estimate import (
    CPU_RATES,
    SPREAD,
    Work,
    estimate_error,
    estimate_line,
    estimate_seconds,
    run_work,
    view_pixels,
)


def test_work_counts_each_stage_in_its_unit():
    views = [(400, 200), (400, 200)]
    work = run_work(
        views,
        geometry_iterations=10,
        geometry_resolution=100,
        rays_per_pixel=4,
        refine_iterations=[(30, True), (5, False)],
        unmasked=True,
    )
    assert view_pixels(400, 200, 100) == 100 * 50  # the geometry trains on views brought to its long side
    assert work.geometry == 10 * 100 * 50
    assert work.masks == 2 * 400 * 200
    assert work.lift == 2 * 400 * 200 * 4
    assert work.refine == 30 * 400 * 200 and work.refine_mapless == 5 * 400 * 200


def test_finished_stages_and_masked_datasets_count_no_work():
    work = run_work([(64, 64)], 10, 0, 1, [], unmasked=False, done=frozenset({"geometry", "lift"}))
    assert work == Work()
    assert estimate_line(work, "cpu") == "estimate: every stage is done already"


def test_the_estimate_is_the_work_times_the_rates_said_as_a_range():
    work = Work(geometry=1e8, lift=1e6, refine=2e7, refine_mapless=1e7)
    seconds = estimate_seconds(work, "cpu")
    assert seconds["geometry"] == pytest.approx(1e8 * CPU_RATES["geometry"])
    assert seconds["refine"] == pytest.approx(2e7 * CPU_RATES["refine"] + 1e7 * CPU_RATES["refine-mapless"])
    total = sum(seconds.values())
    line = estimate_line(work, "cpu")
    assert line.startswith(
        f"estimate: {total / SPREAD / 60:.0f} min to {total * SPREAD / 60:.0f} min with 2 free CPU cores"
    ), line
    largest, smallest = max(seconds, key=seconds.get), min(seconds, key=seconds.get)
    assert line.index(largest) < line.index(smallest)  # the largest stage first


def test_a_device_without_a_measured_rate_says_so():
    assert estimate_seconds(Work(geometry=1.0), "cuda") is None
    assert "no measured rate" in estimate_line(Work(geometry=1.0), "cuda")


def test_estimate_error_is_a_symmetric_factor():
    assert estimate_error(200, 100) == estimate_error(50, 100) == 2.0


def test_a_capture_that_triangulates_points_counts_its_feature_photos():
    work = run_work([(64, 64)], 10, 0, 1, [], unmasked=True, feature_views=[(800, 600), (1024, 768)])
    assert work.points == 800 * 600 + 1024 * 768
    assert estimate_seconds(work, "cpu")["points"] == work.points * CPU_RATES["points"]
    done = run_work([(64, 64)], 10, 0, 1, [], True, frozenset({"points"}), feature_views=[(800, 600)])
    assert done.points == 0.0


def test_feature_photos_are_the_loaded_photos_brought_to_the_points_size():
    from matspray.method.estimate import feature_sizes

    assert feature_sizes([(256, 171), (256, 256)], 4.0, 1024) == [(1024, 684), (1024, 1024)]  # 1024 x 684 as loaded
    assert feature_sizes([(256, 256)], 3.125, 1024) == [(800, 800)]  # smaller than max_size: as loaded
