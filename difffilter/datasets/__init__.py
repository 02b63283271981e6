"""Public data sets by name (:mod:`.registry`, :mod:`.catalog`) and readers of the libRSF text
format (:mod:`.librsf`, :mod:`.ranging`).

    >>> from difffilter import datasets
    >>> folder = datasets.locate("librsf_w3500_skewed")        # local copy, or DataSetMissingError saying how to get it
    >>> rec = datasets.load("librsf_w3500_skewed")             # a RangingRecording
"""

from __future__ import annotations

from pathlib import Path

from .catalog import LIBRSF_W3500, SMARTLOC_BERLIN
from .librsf import COLUMNS, LibrsfFile, detect_kinds, read_librsf
from .ranging import RangingRecording, find_recordings, folder_kind, load_ranging
from .registry import DATASETS, DataSet, DataSetMissingError, cache_dir, fetch, locate, register, search_roots, sha256_of, verify

__all__ = [
    "COLUMNS",
    "DATASETS",
    "DataSet",
    "DataSetMissingError",
    "LIBRSF_W3500",
    "LibrsfFile",
    "RangingRecording",
    "SMARTLOC_BERLIN",
    "cache_dir",
    "detect_kinds",
    "fetch",
    "find_recordings",
    "folder_kind",
    "load",
    "load_ranging",
    "locate",
    "read_librsf",
    "register",
    "search_roots",
    "sha256_of",
    "verify",
]


def load(name: str, root: str | Path | None = None, *, download: bool = False) -> RangingRecording | LibrsfFile:
    """Data set ``name`` read from its folder (:func:`~.registry.locate`): a
    :class:`RangingRecording` for 2-D and 3-D ranging sets; the raw :class:`LibrsfFile` of the input for
    pseudorange sets (the GNSS assembly needs a frame and clock model: the smartLoc loader)."""
    folder = locate(name, root, download=download)  # KeyError listing the names for an unknown one
    ds = DATASETS[name]
    if ds.kind in ("ranging2d", "ranging3d"):
        return load_ranging(folder / ds.inputs[0], folder / ds.truth)
    return read_librsf(folder / ds.inputs[0])
