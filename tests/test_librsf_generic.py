"""The generic libRSF reader (difffilter.datasets.librsf) and the 2-D ranging assembly
(difffilter.datasets.ranging) on excerpts shipped with the tests: columns, kinds detected from
the file, the file's variances, and bad input named by file and line or skipped and counted."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from difffilter.datasets import find_recordings, folder_kind, load_ranging, read_librsf
from difffilter.datasets.librsf import detect_kinds

ASSETS = Path(__file__).parent / "assets" / "librsf"
INPUT, TRUTH = ASSETS / "W3500x_skewed_Input.txt", ASSETS / "W3500x_GT.txt"


def _edit(tmp_path: Path, fn) -> Path:  # type: ignore[no-untyped-def]
    lines = INPUT.read_text().splitlines()
    path = tmp_path / "Edit_Input.txt"
    path.write_text("\n".join(fn(lines)) + "\n")
    return path


def test_kinds_columns_and_variances_of_the_excerpt() -> None:
    rec = read_librsf(INPUT)
    assert rec.kinds() == {"odom2", "range2"} and detect_kinds(INPUT) == {"odom2": 60, "range2": 488}
    first = INPUT.read_text().splitlines()[60].split()  # the first range2 line
    assert rec.tables["range2"][0].tolist() == [float(x) for x in first[1:8]]
    assert rec.where("range2", 0) == f"{INPUT}:61"
    r = load_ranging(INPUT, TRUTH)
    assert r.num_steps == 61 and r.num_anchors == 8 and r.mask.sum() == 488
    assert np.all(r.range_var[r.mask] == 0.25) and np.allclose(
        r.odom_cov[1], np.diag([0.002475007062741, 0.0029091761804288, 0.00039647400273178])
    )
    assert r.truth[5].tolist() == [5.0, 0.0] and r.heading0 == pytest.approx(np.pi) and r.dt[0] == 0 and np.all(r.dt[1:] == 1)
    # the odometry of step k moves with the heading of k-1, then turns (the reference confirms it)
    th = r.heading0 + np.cumsum(r.odom[:, 2])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    step = np.stack([c * r.odom[1:, 0] - s * r.odom[1:, 1], s * r.odom[1:, 0] + c * r.odom[1:, 1]], -1)
    assert np.abs(np.diff(r.truth, axis=0) - step).max() < 0.5
    assert np.allclose(r.anchors[:, 0], [-73.30601630539, -91.872302367159])


def test_shared_truth_files_and_folder_kinds(tmp_path) -> None:
    assert [(n, i.name, g.name) for n, i, g in find_recordings(ASSETS)] == [
        ("W3500x_heavy-tailed", "W3500x_heavy-tailed_Input.txt", "W3500x_GT.txt"),
        ("W3500x_skewed", "W3500x_skewed_Input.txt", "W3500x_GT.txt"),
    ]
    assert folder_kind(ASSETS) == "ranging2d"
    (tmp_path / "G_Input.txt").write_text("pseudorange3 0 2e7 25 1 2 3 5 1 40 40\n")
    assert folder_kind(tmp_path) == "pseudorange"
    shutil.copy(INPUT, tmp_path / "R_Input.txt")
    with pytest.raises(ValueError, match="mix kinds"):
        folder_kind(tmp_path)
    with pytest.raises(FileNotFoundError, match="no data set found"):
        find_recordings(tmp_path / "x" if (tmp_path / "x").mkdir() is None else tmp_path)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda ls: ls[:70] + ["range2 9 1.0 0.25 3.0"] + ls[70:], r"Edit_Input.txt:71: a range2 line needs at least 7 fields"),
        (
            lambda ls: ls[:70] + ["range2 9 abc 0.25 1 2 5 0"] + ls[70:],
            r"Edit_Input.txt:71: field 3 of a range2 line is not a number: 'abc'",
        ),
        (lambda ls: ls[:70] + ["range2 9 nan 0.25 1 2 5 0"] + ls[70:], r"Edit_Input.txt:71: field 3 of a range2 line is not finite"),
        (lambda ls: ls[:5] + ls[6:7] + ls[5:6] + ls[7:], r"Edit_Input.txt:7: odom2 time stamp 6.0 goes back \(line 6 has 7.0\)"),
        (lambda ls: ls[:61] + [ls[60]] + ls[61:], r"Edit_Input.txt:62: anchor 1 measured twice at t=0.0 \(first at line 61\)"),
        (
            lambda ls: [ln.replace(" 0.25 ", " -0.25 ", 1) if i == 65 else ln for i, ln in enumerate(ls)],
            r"Edit_Input.txt:66: range variance must be positive",
        ),
        (lambda ls: [ln for ln in ls if not ln.startswith("range2")], r"no range2 or range3 records"),
        (lambda ls: [ln for ln in ls if not ln.startswith("odom2")], r"no odom2 or odom2diff records"),
    ],
)
def test_bad_input_names_file_and_line(tmp_path, edit, match) -> None:
    with pytest.raises(ValueError, match=match):
        load_ranging(_edit(tmp_path, edit), TRUTH)


def test_missing_files_unknown_kinds_and_thin_steps(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="nope_Input.txt: no such libRSF file"):
        load_ranging(tmp_path / "nope_Input.txt")
    with pytest.raises(FileNotFoundError, match="no such libRSF file"):
        load_ranging(INPUT, tmp_path / "nope_GT.txt")

    def odd(ls: list[str]) -> list[str]:
        keep = [ln for ln in ls if not (ln.startswith("range2 3 ") and ln.split()[6] not in ("1", "2"))]
        return keep + ["imu3 70 1 2 3", "imu3 71 1 2 3", "range2 x y"]

    path = _edit(tmp_path, odd)
    with pytest.raises(ValueError, match="unknown record kind 'imu3'"):
        read_librsf(path, strict=True)
    with pytest.warns(UserWarning, match=r"skipped .*'malformed range2': 1.*'unknown kind imu3': 2"):
        rec = load_ranging(path, TRUTH, min_ranges=3, on_error="skip")
    assert rec.issues == {"malformed range2": 1, "unknown kind imu3": 2, "steps with fewer than 3 ranges": 1}
    assert rec.mask[3].sum() == 0 and rec.mask[4].sum() == 8  # step 3 kept 2 ranges: predicted only


def test_odom2diff_is_converted_with_its_covariance(tmp_path) -> None:
    b, vr, vl, vy, var = 0.5, 1.2, 0.8, 0.05, (0.01, 0.04, 0.09)
    lines = [f"odom2diff {t} {vr} {vl} {vy} {b} {var[0]} {var[1]} {var[2]}" for t in (1, 2)]
    lines += [f"range2 {t} 5.0 0.25 {ax} {ay} {i} 0" for t in (0, 1, 2) for i, (ax, ay) in enumerate([(0, 0), (10, 0), (0, 10)], 1)]
    path = tmp_path / "D_Input.txt"
    path.write_text("\n".join(lines) + "\n")
    rec = load_ranging(path)
    assert np.allclose(rec.odom[1], [(vr + vl) / 2, vy, (vr - vl) / b])
    jac = np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 1.0], [1 / b, -1 / b, 0.0]])
    assert np.allclose(rec.odom_cov[2], jac @ np.diag(var) @ jac.T) and rec.odom_cov[2][0, 2] != 0
    path.write_text(path.read_text().replace(f" {b} ", " 0 ", 1))
    with pytest.raises(ValueError, match="D_Input.txt:1: wheel base must be positive"):
        load_ranging(path)


def test_every_registered_kind_parses(tmp_path) -> None:
    lines = {
        "pseudorange3": "pseudorange3 0 2.1e7 25 1 2 3 7 1 45 40",
        "range3": "range3 0 5 0.1 1 2 3 4",
        "odom3": "odom3 0 1 0 0 0 0 0.1 0.01 0.01 0.01 0.001 0.001 0.001",
        "point3": "point3 0 1 2 3 0 0 0 0 0 0 0 0 0",
        "point2": "point2 0 1 2",
        "angle": "angle 0 3.14 0",
    }
    path = tmp_path / "k.txt"
    path.write_text("\n".join(lines.values()) + "\n")
    rec = read_librsf(path)
    for kind, text in lines.items():
        vals = [float(x) for x in text.split()[1:]]
        ncol = rec.tables[kind].shape[1]
        assert rec.tables[kind][0].tolist() == (vals + [0.0] * ncol)[:ncol], kind
    assert rec.column("range3", "snr")[0] == 0.0 and rec.column("pseudorange3", "elevation")[0] == 45.0


def test_leading_columns_only_and_unread_kinds_counted(tmp_path) -> None:
    path = tmp_path / "c.txt"
    path.write_text("odom3 0 1 0 0 0 0 0.1\npoint3 0 1 2 3\nodom3 1 2 0 0 0 0 0.2 9 9\n")
    with pytest.warns(UserWarning, match="'unread kind point3': 1"):
        rec = read_librsf(path, ["odom3"], columns={"odom3": 7})
    assert rec.tables["odom3"].tolist() == [[0, 1, 0, 0, 0, 0, 0.1], [1, 2, 0, 0, 0, 0, 0.2]]
    with pytest.raises(ValueError, match=r"c.txt:1: a odom3 line needs at least 14 fields, got 8"):
        read_librsf(path, ["odom3"])
    with pytest.raises(ValueError, match="columns .* out of range"):
        read_librsf(path, ["odom3"], columns={"odom3": 20})
