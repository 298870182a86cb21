"""Wire contract shared by every process: message models, tensor blobs, msgpack codec, topics, MQTT helper.

Importing this package never pulls in torch or gymnasium (the Raspberry Pi bridge installs only the base deps).
"""

from protocol.codec import DecodeError, RejectCounter, decode, encode
from protocol.messages import SCHEMA_VERSION
from protocol.tensors import TensorBlob

__all__ = ["SCHEMA_VERSION", "DecodeError", "RejectCounter", "TensorBlob", "decode", "encode"]
