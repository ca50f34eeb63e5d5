"""The base of every configuration section."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["Section"]


class Section(BaseModel):
    """Base of every config model: unknown keys are errors and a loaded config is read-only.

    Each field's attribute docstring becomes its description (`use_attribute_docstrings`), which
    docs/configuration.md is generated from.
    """

    model_config = ConfigDict(
        extra="forbid", validate_assignment=True, frozen=True, use_attribute_docstrings=True
    )
