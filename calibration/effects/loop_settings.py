"""How the closed loop searches (:class:`LoopSettings`), apart from the loop itself so a
command checks its options before the loop's statistics (scipy) load."""

from __future__ import annotations

from dataclasses import dataclass

from calibration.effects.effect_kinds import check_kinds
from calibration.errors import IdentificationError


@dataclass(frozen=True)
class LoopSettings:
    """How the loop searches (see the module docstring for the criterion)."""

    folds: int = 5  # K-fold cross-validation's folds (``leave_one_out`` False)
    leave_one_out: bool = True  # cross-validate by leaving one pose out (exact, hat matrix)
    #: with ``leave_one_out``: score a left-out pose by its predictive deviance, not its
    #: squared error (candidate_scoring.pose_deviance; False: the PRESS, until 2026-11-28)
    loo_deviance: bool = True
    alpha: float = 1e-3  # family-wise false-positive probability per round
    penalty_per_parameter: float | None = None  # σ² per parameter; None: ln(3m)
    max_effects: int = 6
    kinds: tuple[str, ...] | None = None  # candidate kinds offered (None: all)
    fold_seed: int = 0
    rtol: float = 1e-6  # a candidate column this close to the model's span is dropped
    validation_guard: bool = True  # undo a step that makes the validation error worse
    max_rejected: int = 4  # candidates set aside by the validation guard before stopping
    refit_gravity_form: bool = True  # refit the physical form's ratios after a later effect
    #: and beside the shoulder's coupling (its frozen moments kept, its κ fitted again)
    refit_beside_coupling: bool = True
    #: and refitted from a second start too, the coupling rebuilt on that profile's moments
    #: and κ (the joint model's fit): the lower SSE kept
    coupling_on_profile: bool = True
    gravity_first_search: bool = True  # search again with gravity first (second_search)

    def __post_init__(self) -> None:
        if self.folds < 2:
            raise IdentificationError("the closed loop needs at least 2 folds")
        if not 0.0 < self.alpha < 1.0:
            raise IdentificationError("alpha must be in (0, 1)")
        if self.kinds is not None:
            check_kinds(self.kinds)
        if self.max_effects < 0:
            raise IdentificationError(f"max_effects must be >= 0, got {self.max_effects}")
