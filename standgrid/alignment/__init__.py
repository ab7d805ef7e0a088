"""Missions registered to each other on what persists between visits (ground and stems),
placed by one graph of missions (GTSAM) over their GNSS priors and the registrations.

:func:`align_missions` (:mod:`.stage`): landmarks (:mod:`.landmarks`) -> pairwise
registration (:mod:`.register`, small_gicp for the fine step) -> graph and marginals
(:mod:`.graph`) -> corrected placements.
"""

from standgrid.alignment.register import RegisterOptions, Registration
from standgrid.alignment.stage import AlignOptions, AlignResult, align_missions

__all__ = ["AlignOptions", "AlignResult", "RegisterOptions", "Registration", "align_missions"]
