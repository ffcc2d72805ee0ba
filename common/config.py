"""The base of every pydantic config model of the project."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    """Base of every config model: unknown keys are errors, assignments are validated, and a
    number must be finite (``inf`` or ``nan`` is refused, naming the key)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
