"""The libRSF loader on drives cut from the real smartLoc files: a copy loads like the original,
several drives are found in one folder, odometry at its own rate only predicts, and bad input
(missing file, malformed line, time stamps that go back, a satellite twice, an epoch with fewer
than 4 satellites, records of other types or systems) gets an error naming file and line or a
counted warning."""

from __future__ import annotations

import pytest
import torch

from experiments.papers.smartloc import find_drives, load_drive, load_smartloc
from experiments.papers.smartloc.librsf import read_records

from .librsf_fixture import HAVE_DATA, HAVE_FULL, write_drive

pytestmark = pytest.mark.skipif(not HAVE_DATA, reason="the smartLoc excerpt tests/assets/librsf/smartlocx_* is missing")


def _set_field(line: str, index: int, value: str) -> str:
    fields = line.split()
    fields[index] = value
    return " ".join(fields)


def _load(folder, name="Fixture", **kw):  # type: ignore[no-untyped-def]
    return load_drive(folder, input_file=f"{name}_Input.txt", truth_file=f"{name}_GT.txt", **kw)


def test_a_renamed_subset_loads_like_the_original(tmp_path) -> None:
    write_drive(tmp_path, "Copy", start=0.0, stop=30.0)
    write_drive(tmp_path, "Later", start=100.0, stop=120.0)
    assert find_drives(tmp_path) == [("Copy_Input.txt", "Copy_GT.txt"), ("Later_Input.txt", "Later_GT.txt")]
    sub = _load(tmp_path, "Copy")
    assert sub.name == "Copy" and sub.issues == {}
    if HAVE_FULL:  # the whole drive on disk: the first 30 s of it load identically
        full, n, k = load_smartloc(slots="epoch"), sub.num_epochs, sub.num_slots
        assert n == int((full.times < 30.0).sum())
        assert torch.equal(sub.times, full.times[:n]) and torch.equal(sub.truth_ecef, full.truth_ecef[:n])
        assert torch.equal(sub.pseudorange, full.pseudorange[:n, :k]) and torch.equal(sub.mask, full.mask[:n, :k])
        assert torch.equal(sub.speed, full.speed[:n]) and torch.equal(sub.cn0, full.cn0[:n, :k])
        assert torch.equal(sub.constellation, (full.system[:n, :k] == 4).long())
    later = _load(tmp_path, "Later")
    assert float(later.times[0]) >= 100.0 and torch.equal(later.truth_enu[0], torch.zeros(3, dtype=torch.float64))
    with pytest.raises(FileNotFoundError, match="no such folder"):
        find_drives(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no drive found"):
        find_drives(tmp_path / "empty")


def test_odometry_at_its_own_rate_predicts_between_gnss_epochs(tmp_path) -> None:
    """Pseudoranges of every other epoch removed: the steps stay the odometry's time stamps (the
    time base does not move) and the epochs without pseudoranges are masked (prediction only)."""
    full = _load(write_drive(tmp_path, "Full")[0].parent, "Full")
    drop = set(full.times[1::2].tolist())

    def thin(lines: list[str]) -> list[str]:
        return [ln for ln in lines if not (ln.startswith("pseudorange3") and float(ln.split()[1]) in drop)]

    write_drive(tmp_path, "Thin", edit=thin)
    thin_data = _load(tmp_path, "Thin")
    assert torch.equal(thin_data.times, full.times) and torch.equal(thin_data.speed, full.speed)
    assert not bool(thin_data.mask[1::2].any()) and torch.equal(thin_data.mask[::2], full.mask[::2, : thin_data.num_slots])


def test_missing_files_and_folders_are_named(tmp_path) -> None:
    write_drive(tmp_path, "Drive")
    with pytest.raises(FileNotFoundError, match=r"Nope_Input\.txt: no such file \(the input"):
        load_drive(tmp_path, input_file="Nope_Input.txt", truth_file="Drive_GT.txt")
    with pytest.raises(FileNotFoundError, match=r"Nope_GT\.txt: no such file \(the reference"):
        load_drive(tmp_path, input_file="Drive_Input.txt", truth_file="Nope_GT.txt")
    with pytest.raises(FileNotFoundError, match="no such folder"):
        load_drive(tmp_path / "missing")


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (
            lambda ls: ls[:5] + [_set_field(ls[5], 2, "1.2.3")] + ls[6:],
            r"Bad_Input\.txt:6: field 3 of a odom3 line is not a number: '1\.2",
        ),
        (lambda ls: ls[:3] + [" ".join(ls[3].split()[:5])] + ls[4:], r"Bad_Input\.txt:4: a odom3 line needs at least 8 fields, got 5"),
        (lambda ls: ls[:2] + [ls[4], ls[3], ls[2]] + ls[5:], r"Bad_Input\.txt:4: odom3 time stamp .* goes back \(line 3 has"),
        (lambda ls: ls[:-1] + [_set_field(ls[-1], 2, "nan")], r"Bad_Input\.txt:\d+: field 3 of a pseudorange3 line is not finite"),
    ],
    ids=["not-a-number", "too-few-fields", "time-goes-back", "not-finite"],
)
def test_malformed_lines_name_file_and_line(tmp_path, edit, match) -> None:
    write_drive(tmp_path, "Bad", edit=edit)
    with pytest.raises(ValueError, match=match):
        _load(tmp_path, "Bad")


def test_a_satellite_twice_in_one_epoch_is_an_error(tmp_path) -> None:
    def twice(lines: list[str]) -> list[str]:
        i = next(i for i, ln in enumerate(lines) if ln.startswith("pseudorange3"))
        return lines[: i + 1] + [lines[i]] + lines[i + 1 :]

    write_drive(tmp_path, "Twice", edit=twice)
    with pytest.raises(ValueError, match=r"Twice_Input\.txt:\d+: satellite \d+ appears twice at time"):
        _load(tmp_path, "Twice")


def test_thin_epochs_other_systems_and_record_types_are_skipped_and_counted(tmp_path) -> None:
    """An epoch left with 3 satellites is not used for updates (counted, warned); a Galileo line
    is skipped (counted); an unknown record type is skipped (counted); the time base is kept."""
    ref = _load(write_drive(tmp_path, "Ref")[0].parent, "Ref")
    t_thin = float(ref.times[7])

    def damage(lines: list[str]) -> list[str]:
        out, kept = [], 0
        for ln in lines:
            f = ln.split()
            if f[0] == "pseudorange3" and float(f[1]) == t_thin:
                kept += 1
                if kept > 3:
                    continue
            out.append(ln)
        gal = next(ln for ln in out if ln.startswith("pseudorange3") and float(ln.split()[1]) > t_thin + 1.0).split()
        gal[7], gal[8] = "999", "8"  # a Galileo satellite (id, system)
        at = next(i for i, ln in enumerate(out) if ln.startswith("pseudorange3") and float(ln.split()[1]) > t_thin + 1.0)
        return out[:at] + [" ".join(gal), "imu3 0.0 1 2 3"] + out[at:]

    write_drive(tmp_path, "Damaged", edit=damage)
    with pytest.warns(UserWarning) as record:
        data = _load(tmp_path, "Damaged")
    text = " ".join(str(w.message) for w in record)
    assert (
        "1 epochs with fewer than 4 satellites" in text and "1 pseudoranges of systems other than (1, 4)" in text and "1 imu3 lines" in text
    )
    assert data.issues == {"skipped imu3 lines": 1, "pseudoranges of other systems": 1, "epochs with fewer than 4 satellites": 1}
    assert (
        torch.equal(data.times, ref.times)
        and not bool(data.mask[7].any())
        and int(data.mask.sum()) == int(ref.mask.sum()) - int(ref.mask[7].sum())
    )


def test_read_records_counts_and_lines(tmp_path) -> None:
    inp, _ = write_drive(tmp_path, "Lines", stop=1.0)
    rec = read_records(inp)
    n_odom, n_pr = len(rec.values["odom3"]), len(rec.values["pseudorange3"])
    assert n_odom == 5 and n_pr > 20 and rec.lines["odom3"].tolist() == [1, 2, 3, 4, 5]
    assert rec.where("pseudorange3", 0) == f"{inp}:6"


def test_the_shipped_excerpt_is_the_drives_own_lines() -> None:
    """The excerpt the loader and protocol tests read holds the real drive's lines of its spans,
    unchanged and complete (checked against the whole drive when it is on disk)."""
    from .librsf_fixture import INPUT, SOURCE, SPANS, TRUTH, _excerpt

    inside = lambda ln: any(a <= float(ln.split()[1]) < b for a, b in SPANS)  # noqa: E731
    for suffix, name in (("_Input.txt", INPUT), ("_GT.txt", TRUTH)):
        lines = _excerpt(suffix)
        assert len(lines) > 100 and all(inside(ln) for ln in lines)
        if HAVE_FULL:
            assert list(lines) == [ln for ln in (SOURCE / name).read_text().splitlines() if ln.split() and inside(ln)]
