"""bench_lcd.py --photos: the held-out real-photo sequences it uses and the same-place ground
truth it builds by geometric verification (bench_track_words' photo_inliers)."""

import numpy as np
import pytest
from conftest import load_bench, real_photo_folder


@pytest.fixture(scope="module")
def lcd():
    return load_bench("bench_lcd")


def test_photo_sequences_test_on_held_out_frames_only(lcd):
    from orbslam_hgcn.vocabulary.training.photos import HOLDOUT, photo_files

    folder = real_photo_folder()
    train, test = lcd.photo_sequences(folder)
    assert test == photo_files(folder, "heldout")["camvid"]
    assert test[0].name == f"camvid_{HOLDOUT['camvid']:04d}.jpg"
    assert [f.name for f in (train[0], train[-1])] == ["camvid_0420.jpg", "camvid_0559.jpg"]
    assert not set(train) & set(test)


def test_photo_truth_marks_the_same_street_and_not_an_unrelated_photo(lcd, tmp_path):
    folder = real_photo_folder()
    files = [folder / f for f in ("camvid_0620.jpg", "camvid_0621.jpg", "imagenet_sample_0000.jpg")]
    inliers, gt = lcd.photo_truth(files, tmp_path, 40)
    assert (inliers == inliers.T).all() and (gt == gt.T).all()
    assert not np.diag(gt).any() and (np.diag(inliers) == 0).all()
    assert gt[0, 1] and inliers[0, 1] >= 160  # 456 inliers: consecutive frames of one street
    assert not gt[0, 2] and not gt[1, 2]  # an ImageNet photo: chance matches only
    cached = list(tmp_path.glob("inliers_*.npy"))
    assert len(cached) == 1
    np.save(cached[0], np.full((3, 3), 50))  # the cache is what a second call reads
    again, gt2 = lcd.photo_truth(files, tmp_path, 40)
    assert (again == 50).all() and gt2.sum() == 6 and not np.diag(gt2).any()
