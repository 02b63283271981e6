"""difffilter.datasets' registry: names, checksums, licence, the search order, the clear error when
a data set is missing, and the checksum-verified download (a local opener and a file:// URL;
nothing leaves the machine)."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import pytest

from difffilter import datasets
from difffilter.datasets.registry import DataSet

ASSETS = Path(__file__).parent / "assets" / "librsf"
EXCERPT = "W3500x_skewed_Input.txt"


@pytest.fixture
def toy(tmp_path):  # type: ignore[no-untyped-def]
    """A registered data set made of two excerpt files, removed again afterwards."""
    files = {EXCERPT: datasets.sha256_of(ASSETS / EXCERPT), "W3500x_GT.txt": datasets.sha256_of(ASSETS / "W3500x_GT.txt")}
    ds = DataSet(
        name="toy_w3500x",
        folder="toy_w3500x",
        files=files,
        urls={k: (ASSETS / k).resolve().as_uri() for k in files},
        inputs=(EXCERPT,),
        truth="W3500x_GT.txt",
        kind="ranging2d",
        licence="CC BY-SA 4.0",
        citation="T. Pfeifer, libRSF",
        description="excerpt",
    )
    datasets.register(ds)
    yield ds
    del datasets.DATASETS[ds.name]


def test_the_registry_names_files_checksums_and_licence() -> None:
    names = {"smartloc_berlin_potsdamer", "librsf_w3500_heavy_tailed", "librsf_w3500_multimodal", "librsf_w3500_skewed"}
    assert names <= set(datasets.DATASETS)
    for name in names:
        ds = datasets.DATASETS[name]
        assert all(len(h) == 64 and int(h, 16) >= 0 for h in ds.files.values())
        assert set(ds.urls) == set(ds.files) and all(u.startswith("https://") for u in ds.urls.values())
        assert "CC BY-SA 4.0" in ds.licence and ds.citation and "LICENSE.txt" in ds.files
    with pytest.raises(ValueError, match="already registered"):
        datasets.register(datasets.DATASETS["librsf_w3500_skewed"])
    with pytest.raises(KeyError, match="unknown data set 'nope'"):
        datasets.locate("nope")


def test_a_missing_data_set_says_which_and_how_to_get_it(toy, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("DIFFFILTER_DATA", raising=False)
    with pytest.raises(datasets.DataSetMissingError) as err:
        datasets.locate("toy_w3500x", tmp_path / "nowhere")
    msg = str(err.value)
    assert "'toy_w3500x' not found" in msg and str(tmp_path / "nowhere" / "toy_w3500x") in msg
    assert "DIFFFILTER_DATA" in msg and "fetch('toy_w3500x')" in msg and ASSETS.resolve().as_uri() in msg and "CC BY-SA" in msg


def test_root_and_environment_folders_are_found_and_verified(toy, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "root" / "toy_w3500x"
    folder.mkdir(parents=True)
    for f in toy.files:
        shutil.copy(ASSETS / f, folder / f)
    assert datasets.locate("toy_w3500x", tmp_path / "root", verify_files=True) == folder
    monkeypatch.setenv("DIFFFILTER_DATA", str(tmp_path / "root"))
    assert datasets.locate("toy_w3500x") == folder
    rec = datasets.load("toy_w3500x")
    assert rec.num_steps == 61 and rec.num_anchors == 8
    (folder / EXCERPT).write_text((folder / EXCERPT).read_text().replace("range2 0 ", "range2 0.0 ", 1))
    with pytest.raises(ValueError, match=f"{EXCERPT} has sha256 .* the registry expects"):
        datasets.locate("toy_w3500x", verify_files=True)


def test_fetch_verifies_every_download_and_keeps_nothing_broken(toy, tmp_path) -> None:
    served: list[str] = []

    def opener(url: str) -> io.BytesIO:
        served.append(url)
        return io.BytesIO(Path(url.removeprefix("file://")).read_bytes())

    folder = datasets.fetch("toy_w3500x", tmp_path / "cache", opener=opener)
    assert folder == tmp_path / "cache" / "toy_w3500x" and len(served) == 2
    datasets.verify("toy_w3500x", folder)
    datasets.fetch("toy_w3500x", tmp_path / "cache", opener=opener)
    assert len(served) == 2  # verified files already cached are not fetched again

    def tampered(url: str) -> io.BytesIO:
        return io.BytesIO(b"odom2 1 0 0 0 1 1 1\n")

    with pytest.raises(ValueError, match="download of .* has sha256 .* expected"):
        datasets.fetch("toy_w3500x", tmp_path / "other", opener=tampered)
    assert list((tmp_path / "other" / "toy_w3500x").iterdir()) == []  # no partial or wrong file left


def test_fetch_through_urllib_from_a_file_url(toy, tmp_path, monkeypatch) -> None:
    """The default opener (urllib) with the data set's file:// addresses: the download path a user runs."""
    monkeypatch.setenv("DIFFFILTER_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("DIFFFILTER_DATA", raising=False)
    folder = datasets.locate("toy_w3500x", tmp_path / "nowhere", download=True)
    assert folder == tmp_path / "cache" / "toy_w3500x"
    assert (folder / EXCERPT).read_bytes() == (ASSETS / EXCERPT).read_bytes()


@pytest.mark.parametrize(
    "name", ["smartloc_berlin_potsdamer", "librsf_w3500_heavy_tailed", "librsf_w3500_multimodal", "librsf_w3500_skewed"]
)
def test_the_development_copies_match_the_registered_checksums(name: str) -> None:
    try:
        folder = datasets.locate(name)
    except datasets.DataSetMissingError:
        pytest.skip(f"{name}: full data not present (../shared/data/real or DIFFFILTER_DATA)")
    datasets.verify(name, folder)
