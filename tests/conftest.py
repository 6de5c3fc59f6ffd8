"""Shared test fixtures: paths to the real sample data beside the repository (tests that
need it skip without it), and the renders the end-to-end tests run on (made here, from
tests/data, so that those tests never skip)."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
TUM_SAMPLE = SHARED_DATA / "tum_fr3_long_office_household_sample"
EUROC_SAMPLE = SHARED_DATA / "euroc_V1_01_easy_first95"
KITTI_SAMPLE = SHARED_DATA / "kitti00_first160" / "sequences" / "00"
# The real fr3 long-office camera path (ground truth only; tests/data/README.md).
REPLAY_GT = Path(__file__).resolve().parent / "data" / "tum_fr3_long_office_household_groundtruth.txt"


@pytest.fixture
def tum_sample() -> Path:
    if not TUM_SAMPLE.is_dir():
        pytest.skip(f"real TUM sample not found at {TUM_SAMPLE}")
    return TUM_SAMPLE


@pytest.fixture
def euroc_sample() -> Path:
    if not EUROC_SAMPLE.is_dir():
        pytest.skip(f"real EuRoC sample not found at {EUROC_SAMPLE}")
    return EUROC_SAMPLE


@pytest.fixture
def kitti_sample() -> Path:
    """KITTI odometry 00, frames 0-159 (sequence folder; poses in ../../poses/00.txt)."""
    if not KITTI_SAMPLE.is_dir():
        pytest.skip(f"real KITTI sample not found at {KITTI_SAMPLE}")
    return KITTI_SAMPLE


@pytest.fixture
def replay_gt() -> Path:
    """The real fr3 long-office ground truth (TUM format), shipped with the tests."""
    return REPLAY_GT


@pytest.fixture(scope="session")
def synth_replay_100(tmp_path_factory) -> Path:
    """The first 100 frames of the real fr3 long-office camera path replayed in a synthetic
    room (rendered once per test session)."""
    from orbslam_hgcn.synth.sequence import SynthOptions, render_sequence

    out = tmp_path_factory.mktemp("synth_replay_100")
    return render_sequence(out, SynthOptions(trajectory="replay", gt=str(REPLAY_GT), frames=100), progress=False)
