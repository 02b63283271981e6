"""p003 (Yang & Xue 2012): IMM of simplified UKFs for GPS/SINS ultra-tight integration - the
flight simulator (strapdown INS, closed-loop feedback), the 20-state model factory, the
experiment set-up (``experiment=p003_imm_sins``), the mode-switch report and the paired
comparison.  The SINS error model is :class:`difffilter.models.SinsErrorDynamics`."""

from .experiment import empirical_transition, group_scale_q, model_options, p003_imm, p003_learner, p003_mode_model, p003_single, simulate
from .flight import P003_CONFIG, PAPER_PHASES, flight_profile, manoeuvre_flags
from .model import make_p003_model, reference_imm
from .paired import paired_report
from .report import PAPER_SWITCH_STEPS, ModeSwitchReport
from .simulator import P003Scenario, simulate_p003

__all__ = [
    "P003_CONFIG",
    "PAPER_PHASES",
    "PAPER_SWITCH_STEPS",
    "ModeSwitchReport",
    "P003Scenario",
    "empirical_transition",
    "flight_profile",
    "group_scale_q",
    "make_p003_model",
    "manoeuvre_flags",
    "model_options",
    "p003_imm",
    "p003_learner",
    "p003_mode_model",
    "p003_single",
    "paired_report",
    "reference_imm",
    "simulate",
    "simulate_p003",
]
