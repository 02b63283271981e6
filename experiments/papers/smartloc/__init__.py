"""The smartLoc real drive (Berlin Potsdamer Platz; CC BY-SA 4.0, TU Chemnitz, Reisdorf et al.,
VEHICULAR 2016): the data loader, the snapshot least-squares baseline, the odometry +
pseudorange model, synthetic drives on the real geometry, the experiment set-up
(``experiment=smartloc_real``), its filters and the paired block-bootstrap comparison."""

from .data import SmartLocBatch, SmartLocData, default_smartloc_path, find_drives, load_drive, load_smartloc
from .experiment import SmartLocTrajectories, smartloc_learner, smartloc_model, smartloc_simulator, smartloc_synthetic_simulator
from .filters import Shared, SharedPsiColoredUKF, SnapshotWLS
from .model import make_smartloc_model, smartloc_initial_belief
from .paired import block_bootstrap, compare
from .synthetic import PseudorangeErrorModel, calibrate_error_model, simulate_smartloc_drives, synthetic_drive
from .wls import WlsSolution, single_epoch_wls

__all__ = [
    "PseudorangeErrorModel",
    "Shared",
    "SharedPsiColoredUKF",
    "SmartLocBatch",
    "SmartLocData",
    "SmartLocTrajectories",
    "SnapshotWLS",
    "WlsSolution",
    "block_bootstrap",
    "calibrate_error_model",
    "compare",
    "default_smartloc_path",
    "find_drives",
    "load_drive",
    "load_smartloc",
    "make_smartloc_model",
    "simulate_smartloc_drives",
    "single_epoch_wls",
    "smartloc_initial_belief",
    "smartloc_learner",
    "smartloc_model",
    "smartloc_simulator",
    "smartloc_synthetic_simulator",
    "synthetic_drive",
]
