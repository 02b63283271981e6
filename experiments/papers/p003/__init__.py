"""p003 (Yang & Xue 2012): IMM of simplified UKFs for GPS/SINS ultra-tight integration - the
flight simulator (strapdown INS, closed-loop feedback) with its sensor-noise families (paper-faithful,
two-level manoeuvre modes, physically caused noise), the 20-state model factory, the experiment
set-up (``experiment=p003_imm_sins``, ``p003_modes``, ``p003_physical``), the switching-delay
statistics and the paired evaluation on the paper's profile.  The SINS error model is
:class:`difffilter.models.SinsErrorDynamics`."""

from .experiment import (
    empirical_transition,
    group_scale_q,
    learned_from_state,
    model_options,
    p003_imm,
    p003_learner,
    p003_mode_model,
    p003_oracle,
    p003_single,
    simulate,
)
from .flight import LOAD_LIMITS, P003_CONFIG, PAPER_PHASES, flight_profile, manoeuvre_flags, markov_phases, random_phases
from .model import make_p003_model, reference_imm, sojourn_transition
from .noise import NOISE_DEFAULTS, NOISE_FAMILIES, antenna_gain_db, body_elevation, cn0_sigma_scale, true_transition, vibration_scale
from .paired import paper_profile_report
from .report import PAPER_SWITCH_STEPS, switch_delays, switching_rows, time_per_step
from .simulator import P003Scenario, simulate_p003

__all__ = [
    "LOAD_LIMITS",
    "NOISE_DEFAULTS",
    "NOISE_FAMILIES",
    "P003_CONFIG",
    "PAPER_PHASES",
    "PAPER_SWITCH_STEPS",
    "P003Scenario",
    "antenna_gain_db",
    "body_elevation",
    "cn0_sigma_scale",
    "empirical_transition",
    "flight_profile",
    "group_scale_q",
    "learned_from_state",
    "make_p003_model",
    "manoeuvre_flags",
    "markov_phases",
    "model_options",
    "p003_imm",
    "p003_learner",
    "p003_mode_model",
    "p003_oracle",
    "p003_single",
    "paper_profile_report",
    "random_phases",
    "reference_imm",
    "simulate",
    "simulate_p003",
    "sojourn_transition",
    "switch_delays",
    "switching_rows",
    "time_per_step",
    "true_transition",
    "vibration_scale",
]
