"""The one exception the wire protocol raises."""

from __future__ import annotations

__all__ = ["ProtocolError"]


class ProtocolError(ValueError):
    """A message, array, image or key expression does not follow the wire contract.

    Raised by `encode`, `decode` and the key-expression helpers, and by nothing else for bad
    input: a daemon that catches `ProtocolError` around `decode` survives any byte string.
    The text says what was wrong (message type, field, expected versus got).

    Attributes:
        msg_type: wire name of the message concerned (e.g. ``"keyframe"``) when known.
    """

    def __init__(self, message: str, msg_type: str | None = None) -> None:
        super().__init__(message)
        self.msg_type = msg_type
