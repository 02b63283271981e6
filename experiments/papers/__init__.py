"""Everything one paper needs, one package per paper: its simulator and scenario families, its
experiment set-up (what ``conf/experiment/<paper>*.yaml`` builds: simulators for the data
module, filter and learner factories), its report helpers and paired comparisons.

* :mod:`.p000` - UKF for GPS/DR vehicle positioning (Yang & Zhang).
* :mod:`.p001` - UKF under coloured measurement noise, static GPS (Zou, Zhao, Ding).
* :mod:`.p002` - GPS + pedestrian dead reckoning, residual-constrained UKF (Niu & Lian 2017).
* :mod:`.p003` - IMM of simplified UKFs for GPS/SINS ultra-tight integration (Yang & Xue 2012).
* :mod:`.p004` - adaptive EKF/UKF switching for vehicle GNSS/IMU (Li, Zhu, Wang & Lyu).
* :mod:`.smartloc` - the smartLoc real drive (Reisdorf et al., VEHICULAR 2016).

Papers sit on the top floor: they may import every other part of difffilter, nothing imports
them (``tests/test_layering.py``).  Import a paper's package explicitly
(``from experiments.papers.p003 import paper_profile_report``).
"""

__all__ = ["p000", "p001", "p002", "p003", "p004", "smartloc"]
