"""What every packet source is (``Source``) and what it may hand over besides a packet: an
``Oversized`` one, one from a ``Foreign`` sender, or the first from the stream's robot on a new
address (``Handover``)."""

from __future__ import annotations

from dataclasses import dataclass

from ._packets import Packet


@dataclass
class Oversized:
    """What a source returns for a packet longer than its limit (its length in bytes)."""

    n_bytes: int


@dataclass
class Foreign:
    """What a source returns for a packet from a sender that is not the stream's robot."""

    sender: str


@dataclass
class Handover:
    """The first packet of the stream's robot from a new address: the sender fell silent for
    ``silence_s`` seconds and the same host came back on a new port (a restarted robot), so
    ``sender`` (``HOST:PORT``) is the stream's sender from now on, instead of ``previous``.
    ``data``: the packet, or ``Oversized`` when it was longer than the source's limit."""

    data: bytes | Oversized
    sender: str
    previous: str
    silence_s: float


class Source:
    """Yields ``bytes`` (one packet each) or ``Packet``s; ``None`` on a read timeout; an
    ``Oversized``, ``Foreign`` or ``Handover`` item for what is not simply the next packet.

    ``dropped``: packets the operating system dropped before they could be read, where it
    says (else ``None``); ``foreign``: packets not used per other sender."""

    description = ""
    dropped: int | None = None
    foreign: dict[str, int] = {}

    def open(self) -> None: ...

    def read(self, timeout: float) -> bytes | Packet | Oversized | Foreign | Handover | None:
        raise NotImplementedError

    def count_dropped(self) -> int | None:
        """Packets dropped so far before they could be read (``None``: not known)."""
        return self.dropped

    def close(self) -> None: ...
