"""The ``[screening]`` block of a study: which observer-screening rules a study applies, with their thresholds.

The rules themselves, what each measures and how the thresholds are calibrated to the design, are
:mod:`server.analysis.screening`.
"""

from __future__ import annotations

from typing import Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

RULES = ("catch", "straight_lining", "z_outlier", "bt500", "correlation", "disagreement", "fast")
Rule = Literal["catch", "straight_lining", "z_outlier", "bt500", "correlation", "disagreement", "fast"]


class Screening(BaseModel):
    """Which observer-screening rules a study applies, with their thresholds (the standards' defaults)."""

    model_config = ConfigDict(extra="forbid")

    rules: list[Rule] = Field(default_factory=lambda: ["catch"], max_length=len(RULES),
                              description='the rules applied ("all": every one): catch, straight_lining, '
                                          "z_outlier, bt500, correlation, fast")
    min_variance: float = Field(0.15, ge=0, le=4, description="straight_lining: least variance of the raw answers")
    z_limit: float = Field(3.29, gt=0, le=10, description="z_outlier: |z| of a vote counted as an outlier")
    max_rejected_share: float = Field(0.2, ge=0, le=1, description="z_outlier: most outlier votes (share)")
    bt500_ratio: float = Field(0.05, ge=0, le=1, description="bt500: (P+Q)/(J*R) above which a participant may "
                               "be rejected")
    bt500_balance: float = Field(0.3, ge=0, le=1, description="bt500: |P-Q|/(P+Q) below which they are")
    correlation_method: Literal["pearson", "spearman"] = "pearson"
    max_correlation_threshold: float = Field(0.7, ge=-1, le=1, description="correlation: the threshold is "
                                             "min(this, mean - sd of the panel's correlations)")
    max_disagreement: float = Field(1.5, ge=0, le=16, description="disagreement (fixed thresholds): most "
                                    "variance of the differences from the others' mean votes (a uniformly random "
                                    "answerer's is about 2 plus the comparison scores' variance)")
    max_fast_share: float = Field(0.2, ge=0, le=1, description="fast: most votes given before one playback ended")
    thresholds: Literal["design", "fixed"] = Field("design", description="design: the thresholds of "
                                                   "straight_lining, z_outlier, bt500, correlation and fast "
                                                   "calibrated to the study's design by simulation "
                                                   "(screening_design; the fixed values above are not used); "
                                                   "fixed: the values above")
    false_flag_rate: float = Field(0.01, gt=0, le=0.5, description="design thresholds: the chance that a good "
                                   "observer is screened out by any calibrated rule")
    min_power: float = Field(0.9, ge=0, le=1, description="design thresholds: a rule that catches fewer of the "
                             "bad observers it is meant for says the design is too small for it and flags nobody")

    @field_validator("rules", mode="before")
    @classmethod
    def all_rules(cls, value: Any) -> Any:
        if value == "all":
            return list(RULES)
        if isinstance(value, str):
            raise ValueError(f'rules must be a list of rule names or "all", got {value!r}')
        return value

    @model_validator(mode="after")
    def distinct(self) -> Self:
        if len(set(self.rules)) != len(self.rules):
            raise ValueError("rules lists a rule more than once")
        return self
