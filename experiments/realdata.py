"""The real-data protocol on libRSF drives (smartLoc format): train on contiguous blocks, choose on
a held-out validation block from several seeds, test with paired block-bootstrap intervals.

    python experiments/realdata.py                                   # smartLoc Berlin, folds A and B, 5 seeds
    python experiments/realdata.py folder=/data/drives               # every <name>_Input.txt + <name>_GT.txt of a folder
    python experiments/realdata.py folder=../shared/data/real/librsf_ranging_w3500   # range2 data: the 2-D ranging protocol
    python experiments/realdata.py folder=tests/assets/librsf/range3    # range3 (+ odom3 or none): the same protocol in 3-D
    python experiments/realdata.py folder=[/data/set1,/data/set2]   # the data sets of several folders (one kind)
    python experiments/realdata.py transfer_from=outputs/realdata/smartloc/<run> folder=/data/other
    python experiments/realdata.py realdata.horizons=[1,2,4]          # stability check (4x the epochs)
    python experiments/realdata.py evaluate_from=outputs/realdata/smartloc/<run>   # recompute a run's test tables (no training)
    python experiments/realdata.py evaluate_from=<run> compare_with=<other run>     # + paired differences against the other run's rows

The logic is in experiments.papers.smartloc.protocol / .report (pseudoranges) and
experiments.ranging.protocol / .report (2-D and 3-D ranging, conf/realdata_ranging); results.md, summary.json, the
noise-model figures and TensorBoard events go to the Hydra run directory.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

# The research tree (experiments/) is not installed: make it importable from the repository root.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# difffilter before torch, so that OpenMP's idle workers sleep instead of spinning (difffilter/_openmp.py)
importlib.import_module("difffilter")

import logging  # noqa: E402
import warnings  # noqa: E402

import hydra  # noqa: E402
import torch  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig, OmegaConf  # noqa: E402

from difffilter.datasets import folder_kind  # noqa: E402
from experiments.papers.smartloc.report import resolve_config, run_evaluation, run_protocol, run_transfer  # noqa: E402
from experiments.ranging.report import run_ranging  # noqa: E402

log = logging.getLogger(__name__)


def folder_list(folder: object) -> list[str]:
    """``folder=`` as a list of folders: none (``null``), one path, or a list of paths."""
    if folder is None or folder == "":
        return []
    if isinstance(folder, str):
        return [folder]
    return [str(f) for f in folder]  # type: ignore[attr-defined]


def data_kind(folders: list[str]) -> str:
    """The one kind (``ranging2d`` / ``ranging3d`` / ``pseudorange``) of every folder's data sets; ``ValueError``
    naming the folders when they differ."""
    kinds = {f: folder_kind(f) for f in folders}
    if len(set(kinds.values())) > 1:
        raise ValueError(f"the folders hold data of different kinds {kinds}; run each kind on its own")
    return next(iter(kinds.values()))


@hydra.main(version_base="1.3", config_path="../conf", config_name="realdata")
def main(cfg: DictConfig) -> None:
    """Run the protocol (or a transfer evaluation, or a re-evaluation of a finished run) and print the report."""
    torch.set_num_threads(int(cfg.threads))
    warnings.filterwarnings("ignore", module="pytorch_lightning")
    out = HydraConfig.get().runtime.output_dir
    folders = folder_list(cfg.folder)
    if folders and data_kind(folders) in ("ranging2d", "ranging3d"):
        run_ranging(folders, OmegaConf.to_container(cfg.realdata_ranging, resolve=True), out)  # type: ignore[arg-type]
        print(open(f"{out}/results.md").read())
        log.info("results written to %s", out)
        return
    spec = resolve_config(OmegaConf.to_container(cfg.realdata, resolve=True), folders or None)  # type: ignore[arg-type]
    if cfg.evaluate_from:
        run_evaluation(cfg.evaluate_from, out, compare_with=cfg.get("compare_with"))
    elif cfg.transfer_from:
        run_transfer(cfg.transfer_from, spec, out)
    else:
        run_protocol(spec, out, workers=int(cfg.workers))
    print(open(f"{out}/results.md").read())
    log.info("results written to %s", out)


if __name__ == "__main__":
    main()
