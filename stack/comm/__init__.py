"""Zenoh sessions, key names, message types and the radio model. Imports nothing else of ours."""

from .keys import Keys
from .messages import MessageError, decode, encode, receive
from .radio import RadioConfig, RadioModel
from .session import SessionConfig, open_session

__all__ = ["Keys", "MessageError", "decode", "encode", "receive", "RadioConfig", "RadioModel", "SessionConfig", "open_session"]
