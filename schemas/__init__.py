"""Wire format (msgpack) and Zenoh key space. See docs/design.md, "Wire format"."""

from .keys import KeySpace, check_id, tracker_id
from .messages import (
    KINDS,
    MEASUREMENT_KINDS,
    SCHEMA_VERSION,
    Message,
    SchemaError,
    decode,
    encode,
    encode_estimate,
    encode_measurement,
    to_estimate,
    to_measurement,
    validate,
)

__all__ = [
    "KINDS", "MEASUREMENT_KINDS", "SCHEMA_VERSION", "KeySpace", "Message", "SchemaError", "check_id", "tracker_id",
    "decode", "encode", "encode_estimate", "encode_measurement", "to_estimate", "to_measurement", "validate",
]
