"""What every packet source is (``Source``) and what it may hand over besides a packet: an
``Oversized`` one, or one from a ``Foreign`` sender."""

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


class Source:
    """Yields ``bytes`` (one packet each) or ``Packet``s; ``None`` on a read timeout.

    ``dropped``: packets the operating system dropped before they could be read, where it
    says (else ``None``); ``foreign``: packets not used per other sender."""

    description = ""
    dropped: int | None = None
    foreign: dict[str, int] = {}

    def open(self) -> None: ...

    def read(self, timeout: float) -> bytes | Packet | Oversized | Foreign | None:
        raise NotImplementedError

    def count_dropped(self) -> int | None:
        """Packets dropped so far before they could be read (``None``: not known)."""
        return self.dropped

    def close(self) -> None: ...
