"""Public data sets by name: where to get them, their licence, the sha256 of every file, and a
local folder or a checksum-verified download cache to read them from.

A data set is a folder of files (libRSF text files for the ones registered here).
:func:`locate` finds it, in this order:

1. ``root/<folder>`` when ``root`` is given;
2. ``$DIFFFILTER_DATA/<folder>``;
3. ``<ancestor>/shared/data/real/<folder>`` for the nearest ancestor of the repository that has
   one (the development checkout's ``../shared``);
4. the download cache ``$DIFFFILTER_CACHE`` (default ``~/.cache/difffilter/data``)
   ``/<folder>``, filled by :func:`fetch` (``download=True``).

A folder counts only when every file of the data set is there; with ``verify=True`` every file's
sha256 must also match the registry.  A data set found nowhere raises :class:`DataSetMissingError`
naming the data set, the places searched, and how to get it (the upstream addresses and the
licence).  :func:`fetch` downloads into a temporary file, checks the sha256 and only then moves
the file into place, so a broken or tampered download never becomes a cached file.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import urllib.request
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

__all__ = [
    "DATASETS",
    "DataSet",
    "DataSetMissingError",
    "cache_dir",
    "fetch",
    "locate",
    "register",
    "search_roots",
    "sha256_of",
    "verify",
]

_COMMIT = "d54801a232af02c0cda6012dabd3dea6c5fd77c5"
_RAW = f"https://raw.githubusercontent.com/TUC-ProAut/libRSF/{_COMMIT}/datasets"
_CC_BY_SA = (
    "Creative Commons Attribution-ShareAlike 4.0 International (CC BY-SA 4.0); "
    "legal text in LICENSE.txt, https://creativecommons.org/licenses/by-sa/4.0/. "
    "Credit the authors; share adaptations of the data under the same licence."
)


class DataSetMissingError(FileNotFoundError):
    """A registered data set is not in any searched folder (the message says how to get it)."""


@dataclass(frozen=True)
class DataSet:
    """One registered data set.

    Attributes:
        name: registry key.
        folder: folder name under a data root.
        files: ``{file name: sha256 hex}`` of every file the data set needs.
        urls: ``{file name: download address}`` (a subset of ``files``).
        inputs: the libRSF input file(s) of this data set (sensor records).
        truth: the ground-truth file.
        kind: ``"pseudorange"`` (GNSS), ``"ranging2d"`` or ``"ranging3d"`` (2-D / 3-D ranging to anchors).
        licence: licence text shown with the data.
        citation: what users of the data must cite.
        description: one paragraph.
    """

    name: str
    folder: str
    files: Mapping[str, str]
    urls: Mapping[str, str]
    inputs: tuple[str, ...]
    truth: str
    kind: str
    licence: str
    citation: str
    description: str
    extra: Mapping[str, str] = field(default_factory=dict)

    def how_to_get(self) -> str:
        """A human-readable paragraph: where the files come from and under what licence."""
        urls = "\n".join(f"  {name}: {url}" for name, url in self.urls.items())
        return (
            f"Data set {self.name!r} ({self.description}). Put its files in a folder "
            f"'<root>/{self.folder}' and pass root=<root> or set DIFFFILTER_DATA=<root>, or call "
            f"difffilter.datasets.fetch({self.name!r}) to download and verify them:\n{urls}\n"
            f"Licence: {self.licence}\nCite: {self.citation}"
        )


DATASETS: dict[str, DataSet] = {}


def register(dataset: DataSet) -> DataSet:
    """Add ``dataset`` to :data:`DATASETS` (a name registered twice is an error)."""
    if dataset.name in DATASETS:
        raise ValueError(f"data set {dataset.name!r} is already registered")
    missing = set(dataset.inputs) | {dataset.truth}
    if not missing <= set(dataset.files):
        raise ValueError(f"data set {dataset.name!r}: inputs/truth {sorted(missing - set(dataset.files))} have no checksum")
    DATASETS[dataset.name] = dataset
    return dataset


def _get(name: str) -> DataSet:
    if name not in DATASETS:
        raise KeyError(f"unknown data set {name!r}; registered: {sorted(DATASETS)}")
    return DATASETS[name]


def cache_dir() -> Path:
    """``$DIFFFILTER_CACHE`` or ``~/.cache/difffilter/data``: where :func:`fetch` writes."""
    env = os.environ.get("DIFFFILTER_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "difffilter" / "data"


def search_roots(root: str | Path | None = None) -> list[Path]:
    """The data roots :func:`locate` searches, in order (module docstring)."""
    roots: list[Path] = []
    if root is not None:
        roots.append(Path(root))
    env = os.environ.get("DIFFFILTER_DATA")
    if env:
        roots.append(Path(env))
    repo = Path(__file__).resolve().parents[2]
    for up in repo.parents:  # ../shared next to the repository (or next to a folder holding worktrees)
        if (up / "shared" / "data" / "real").is_dir():
            roots.append(up / "shared" / "data" / "real")
            break
    roots.append(cache_dir())
    return roots


def sha256_of(path: str | Path, *, chunk: int = 1 << 20) -> str:
    """The sha256 hex digest of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def verify(name: str, folder: str | Path) -> None:
    """Raise ``ValueError`` naming the file if any of ``name``'s files in ``folder`` is missing or
    has another sha256 than the registry's."""
    ds = _get(name)
    for fname, digest in ds.files.items():
        path = Path(folder) / fname
        if not path.is_file():
            raise ValueError(f"data set {name!r}: {path} is missing")
        got = sha256_of(path)
        if got != digest:
            raise ValueError(f"data set {name!r}: {path} has sha256 {got}, the registry expects {digest}")


def locate(name: str, root: str | Path | None = None, *, download: bool = False, verify_files: bool = False) -> Path:
    """The folder holding every file of data set ``name`` (search order: module docstring).

    Args:
        name: a key of :data:`DATASETS`.
        root: a data root searched first (``root/<folder>``).
        download: fetch into the cache when no folder has the files.
        verify_files: check every file's sha256 in the folder found.

    Raises:
        KeyError: ``name`` is not registered.
        DataSetMissingError: the data set is nowhere and ``download`` is False.
    """
    ds = _get(name)
    searched = []
    for base in search_roots(root):
        folder = base / ds.folder
        searched.append(str(folder))
        if all((folder / f).is_file() for f in ds.files):
            if verify_files:
                verify(name, folder)
            return folder
    if download:
        return fetch(name)
    raise DataSetMissingError(f"data set {name!r} not found (searched: {', '.join(searched)}).\n{ds.how_to_get()}")


Opener = Callable[[str], IO[bytes]]


def fetch(name: str, cache: str | Path | None = None, *, opener: Opener | None = None) -> Path:
    """Download data set ``name`` into ``cache/<folder>`` (default :func:`cache_dir`), verifying
    every file's sha256; files already there with the right checksum are kept.

    Args:
        name: a key of :data:`DATASETS`.
        cache: the cache root.
        opener: ``url -> binary file object`` (default ``urllib.request.urlopen``; tests pass
            their own so that nothing leaves the machine).

    Returns:
        The folder holding the verified files.

    Raises:
        ValueError: a downloaded file's sha256 differs from the registry's (nothing is kept), or
            a file of the data set has no download address.
    """
    ds = _get(name)
    open_url = opener or urllib.request.urlopen
    folder = Path(cache if cache is not None else cache_dir()) / ds.folder
    folder.mkdir(parents=True, exist_ok=True)
    for fname, digest in ds.files.items():
        target = folder / fname
        if target.is_file() and sha256_of(target) == digest:
            continue
        if fname not in ds.urls:
            raise ValueError(f"data set {name!r}: file {fname} has no download address; put it in {folder} by hand")
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{fname}.", suffix=".part")
        try:
            with os.fdopen(fd, "wb") as out, open_url(ds.urls[fname]) as src:
                shutil.copyfileobj(src, out)
            got = sha256_of(tmp)
            if got != digest:
                raise ValueError(f"data set {name!r}: download of {fname} from {ds.urls[fname]} has sha256 {got}, expected {digest}")
            os.replace(tmp, target)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
    return folder
