"""Ground-truth loaders (.mat/.txt/.csv/.npy) and the lcd command's input errors."""

import cv2
import numpy as np
import pytest

from orbslam_hgcn.cli import main
from orbslam_hgcn.errors import DatasetError
from orbslam_hgcn.placerec.data import ImageSource, load_ground_truth, save_ground_truth


def _gt(n=7, seed=0):
    rng = np.random.default_rng(seed)
    g = np.tril(rng.random((n, n)) < 0.3, -1)
    return g | g.T


@pytest.mark.parametrize("suffix", [".mat", ".txt", ".csv", ".npy"])
def test_ground_truth_round_trip(tmp_path, suffix):
    gt = _gt()
    path = tmp_path / f"truth{suffix}"
    save_ground_truth(path, gt)
    got = load_ground_truth(path, n_images=7)
    assert got.dtype == bool
    np.testing.assert_array_equal(got, gt)


def test_one_triangle_is_symmetrised_and_mat_variable_found_by_shape(tmp_path):
    import scipy.io

    lower = np.tril(_gt(), -1).astype(float) * 0.5
    scipy.io.savemat(tmp_path / "x.mat", {"loops": lower, "name": "seq"})
    got = load_ground_truth(tmp_path / "x.mat")
    np.testing.assert_array_equal(got, _gt())


def test_text_matrix_with_comments_and_commas(tmp_path):
    p = tmp_path / "gt.txt"
    p.write_text("# loops\n0, 0, 1\n0 0 0\n\n1,0,0\n")
    got = load_ground_truth(p)
    assert got[0, 2] and got[2, 0] and got.sum() == 2


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("ragged.txt", "0 1\n1 0 0\n", r"ragged.txt:2: row has 3 values, line 1 has 2"),
        ("word.txt", "0 x\n1 0\n", r"word.txt:1: not a number"),
        ("rect.txt", "0 1 0\n1 0 0\n", r"rect.txt: ground truth must be a square matrix, found shape \(2, 3\)"),
        ("bad.mat", "not a mat file", r"bad.mat: not a readable MATLAB"),
        ("bad.npy", "garbage", r"bad.npy: not a readable .npy"),
        ("empty.txt", "# nothing\n", r"empty.txt: ground-truth file is empty"),
        ("gt.xyz", "0", r"gt.xyz: unknown ground-truth format"),
    ],
)
def test_bad_ground_truth_files_name_the_file(tmp_path, name, content, message):
    p = tmp_path / name
    p.write_text(content)
    with pytest.raises(DatasetError, match=message):
        load_ground_truth(p)


def test_ground_truth_size_must_match_image_count(tmp_path):
    p = tmp_path / "gt.npy"
    np.save(p, np.zeros((5, 5)))
    with pytest.raises(DatasetError, match=r"gt.npy: ground truth is 5x5 but the test sequence has 6 images"):
        load_ground_truth(p, n_images=6)
    with pytest.raises(DatasetError, match="not found"):
        load_ground_truth(tmp_path / "missing.mat")


def _image_folder(path, n, seed=0):
    path.mkdir()
    rng = np.random.default_rng(seed)
    for i in range(n):
        cv2.imwrite(str(path / f"img{i}.png"), rng.integers(0, 255, (60, 80), dtype=np.uint8))
    return path


def test_image_source_reads_folder_in_order_with_stride(tmp_path):
    folder = _image_folder(tmp_path / "seq", 5)
    src = ImageSource(folder, stride=2)
    assert len(src) == 3 and src.total == 5
    imgs = list(src)
    np.testing.assert_array_equal(imgs[1], cv2.imread(str(folder / "img2.png"), cv2.IMREAD_GRAYSCALE))


def test_lcd_cli_reports_shape_mismatch(tmp_path, capsys):
    train = _image_folder(tmp_path / "train", 4, seed=1)
    test = _image_folder(tmp_path / "test", 6, seed=2)
    gt = tmp_path / "gt.txt"
    save_ground_truth(gt, np.zeros((4, 4)))
    code = main(["lcd", "--train", str(train), "--test", str(test), "--gt", str(gt), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert f"{gt}: ground truth is 4x4 but the test sequence has 6 selected images" in err
    assert "Traceback" not in err
    # a full-sequence matrix is cut down to the strided images, so it is no error then
    code = main(["lcd", "--train", str(train), "--test", str(test), "--gt", str(gt), "--stride", "2",
                 "--method", "nope", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "unknown method 'nope'" in capsys.readouterr().err


def test_lcd_cli_missing_default_ground_truth(tmp_path, capsys):
    train = _image_folder(tmp_path / "train", 3, seed=1)
    test = _image_folder(tmp_path / "test", 3, seed=2)
    code = main(["lcd", "--train", str(train), "--test", str(test), "--out", str(tmp_path / "o")])
    assert code == 2
    assert "no --gt given and no loop_gt.npy" in capsys.readouterr().err


def test_lcd_cli_missing_vocabulary_file(tmp_path, capsys):
    train = _image_folder(tmp_path / "train", 3, seed=1)
    test = _image_folder(tmp_path / "test", 3, seed=2)
    np.save(test / "loop_gt.npy", np.zeros((3, 3)))
    missing = tmp_path / "nowhere.npz"
    code = main(["lcd", "--train", str(train), "--test", str(test), "--vocab", str(missing), "--min-gap", "1",
                 "--out", str(tmp_path / "o")])
    assert code == 2
    assert f"{missing}: vocabulary file not found" in capsys.readouterr().err
