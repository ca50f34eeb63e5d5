"""The wire contract: messages, array codec, key expressions (no torch, no zenoh).

Typical use::

    from cpslam import protocol
    from cpslam.protocol import keys

    payload = protocol.encode(protocol.Ack(agent_id="a0", seq=12))
    msg = protocol.decode(payload, expected=protocol.Ack)    # ProtocolError on bad input
    key = keys.server_agent_ack("demo", "a0")                 # cpslam/demo/server/agent/a0/ack

docs/protocol.md describes the bytes on the wire for readers without this package.
"""

from cpslam.protocol import keys
from cpslam.protocol.arrays import DTYPES, FILTERS, ArraySpec, array_from_wire, array_to_wire
from cpslam.protocol.base import PROTOCOL_VERSION, Message, WireModel
from cpslam.protocol.codec import (
    MAX_MESSAGE_BYTES,
    MESSAGE_TYPES,
    decode,
    encode,
    encoded_size,
    max_bytes,
)
from cpslam.protocol.delivery import Refusal, UpdateAck
from cpslam.protocol.errors import ProtocolError
from cpslam.protocol.messages import (
    XYZ_STEP_M,
    DecoderWeights,
    FramePoses,
    KeyframeImage,
    KeyframeImageRequest,
    KeyframeMsg,
    SubmapDelta,
    descriptor_codes,
)
from cpslam.protocol.updates import (
    Ack,
    Control,
    ErrorReply,
    ForeignPoints,
    GroupDecoder,
    ServerUpdate,
    Status,
)

__all__ = [
    "PROTOCOL_VERSION",
    "DTYPES",
    "MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "ArraySpec",
    "Message",
    "WireModel",
    "ProtocolError",
    "encode",
    "decode",
    "encoded_size",
    "max_bytes",
    "array_to_wire",
    "FILTERS",
    "XYZ_STEP_M",
    "array_from_wire",
    "keys",
    "KeyframeMsg",
    "descriptor_codes",
    "SubmapDelta",
    "DecoderWeights",
    "FramePoses",
    "KeyframeImageRequest",
    "KeyframeImage",
    "ServerUpdate",
    "ForeignPoints",
    "GroupDecoder",
    "Ack",
    "Status",
    "Control",
    "ErrorReply",
    "UpdateAck",
    "Refusal",
]
