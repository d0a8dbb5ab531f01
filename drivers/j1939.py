"""SAE J1939 / ISO 11783 framing and address claiming, just what the box needs.

Pure logic, no I/O: the CAN link feeds received frames to :class:`AddressClaimer` and sends the
frames it returns. Modelled on J1939-81 (network management):

* A node claims its preferred address with an ADDRESS CLAIMED message (PGN 60928) carrying its
  64-bit NAME and may send nothing else for 250 ms. If another node claims the same address, the
  LOWER NAME wins: the winner repeats its claim, the loser moves to another address (only if its
  NAME says "arbitrary address capable") or sends CANNOT CLAIM (source address 254) and falls
  silent.
* A REQUEST (PGN 59904) for PGN 60928 is answered with our claim (or CANNOT CLAIM).
"""
from __future__ import annotations

from dataclasses import dataclass

PGN_REQUEST = 59904            # 0xEA00, PDU1
PGN_ADDRESS_CLAIMED = 60928    # 0xEE00, PDU1
PGN_AISO = 64770               # 0xFD02 ISO 11783-7 all implements stop operations switch state
PGN_WBSD = 65096               # 0xFE48 ISO 11783-7 wheel-based speed and distance
ADDR_GLOBAL = 255
ADDR_NULL = 254                # "cannot claim" / no address yet
CLAIM_VETO_S = 0.25            # J1939-81: wait this long after a claim before using the address


# ---- identifiers ---------------------------------------------------------------------------------
def make_id(priority: int, pgn: int, sa: int, da: int = ADDR_GLOBAL) -> int:
    """29-bit identifier: priority (3 bits), PGN (18 bits, with DA in PS for PDU1), SA."""
    if not 0 <= priority <= 7 or not 0 <= sa <= 255 or not 0 <= pgn < (1 << 18):
        raise ValueError("priority 0..7, sa 0..255, pgn < 2^18")
    pf = (pgn >> 8) & 0xFF
    if pf < 240:                                  # PDU1: PS is the destination address
        pgn = (pgn & 0x3FF00) | (da & 0xFF)
    return (priority << 26) | (pgn << 8) | sa


@dataclass(frozen=True)
class J1939Id:
    priority: int
    pgn: int          # with PS cleared for PDU1
    sa: int
    da: int           # ADDR_GLOBAL for PDU2

    @classmethod
    def parse(cls, can_id: int) -> "J1939Id":
        priority = (can_id >> 26) & 0x7
        raw = (can_id >> 8) & 0x3FFFF
        sa = can_id & 0xFF
        pf = (raw >> 8) & 0xFF
        if pf < 240:
            return cls(priority, raw & 0x3FF00, sa, raw & 0xFF)
        return cls(priority, raw, sa, ADDR_GLOBAL)


# ---- NAME --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class J1939Name:
    """The 64-bit NAME (J1939-81 / ISO 11783-5). ``value`` is sent little-endian."""

    identity_number: int = 0          # 21 bits
    manufacturer_code: int = 0        # 11 bits
    ecu_instance: int = 0             # 3 bits
    function_instance: int = 0        # 5 bits
    function: int = 0                 # 8 bits
    vehicle_system: int = 0           # 7 bits
    vehicle_system_instance: int = 0  # 4 bits
    industry_group: int = 2           # 3 bits (2 = agricultural and forestry)
    arbitrary_address_capable: bool = True

    @property
    def value(self) -> int:
        return ((self.identity_number & 0x1FFFFF)
                | (self.manufacturer_code & 0x7FF) << 21
                | (self.ecu_instance & 0x7) << 32
                | (self.function_instance & 0x1F) << 35
                | (self.function & 0xFF) << 40
                | (self.vehicle_system & 0x7F) << 49
                | (self.vehicle_system_instance & 0xF) << 56
                | (self.industry_group & 0x7) << 60
                | int(bool(self.arbitrary_address_capable)) << 63)

    def to_bytes(self) -> bytes:
        return self.value.to_bytes(8, "little")

    @classmethod
    def from_value(cls, v: int) -> "J1939Name":
        if not 0 <= v < (1 << 64):
            raise ValueError("a NAME is 64 bits")
        return cls(v & 0x1FFFFF, (v >> 21) & 0x7FF, (v >> 32) & 0x7, (v >> 35) & 0x1F,
                   (v >> 40) & 0xFF, (v >> 49) & 0x7F, (v >> 56) & 0xF, (v >> 60) & 0x7,
                   bool(v >> 63))

    @classmethod
    def parse(cls, text: str) -> "J1939Name":
        """From a config string: an integer in any base Python accepts ("0xA00C...")."""
        return cls.from_value(int(str(text).strip().replace("_", ""), 0))


# ---- address claim -----------------------------------------------------------------------------
class ClaimState:
    NONE = "none"
    WAIT_VETO = "claiming"
    CLAIMED = "claimed"
    CANNOT_CLAIM = "cannot claim"


@dataclass(frozen=True)
class Frame:
    can_id: int
    data: bytes


class AddressClaimer:
    """J1939-81 address claim as a small state machine. Time is passed in (seconds, monotonic),
    so it is deterministic under test. Every method returns the frames to send."""

    def __init__(self, name: J1939Name, preferred: int, lowest: int = 128, highest: int = 247):
        if not 0 <= preferred <= 253:
            raise ValueError("preferred address must be 0..253")
        self.name = name
        self.preferred = preferred
        self.lowest, self.highest = lowest, highest
        self.state = ClaimState.NONE
        self.address = ADDR_NULL           # the address being claimed or held
        self.claimed_at: float | None = None
        self.contests = 0                  # contested claims seen
        self.lost = 0                      # contests we lost
        self.others: dict[int, int] = {}   # address -> NAME value of other claimants
        self._tried: set[int] = set()

    # frames
    def _claim_frame(self, address: int) -> Frame:
        return Frame(make_id(6, PGN_ADDRESS_CLAIMED, address, ADDR_GLOBAL), self.name.to_bytes())

    def start(self, now_s: float) -> list[Frame]:
        self._tried = {self.preferred}
        return self._claim(self.preferred, now_s)

    def _claim(self, address: int, now_s: float) -> list[Frame]:
        self.address = address
        self.state = ClaimState.WAIT_VETO
        self.claimed_at = now_s
        return [self._claim_frame(address)]

    def tick(self, now_s: float) -> list[Frame]:
        if (self.state == ClaimState.WAIT_VETO and self.claimed_at is not None
                and now_s - self.claimed_at >= CLAIM_VETO_S):
            self.state = ClaimState.CLAIMED
        return []

    @property
    def usable(self) -> bool:
        return self.state == ClaimState.CLAIMED

    def _next_free(self) -> int | None:
        for a in list(range(self.lowest, self.highest + 1)):
            if a not in self._tried and a not in self.others:
                return a
        return None

    def on_frame(self, can_id: int, data: bytes, now_s: float) -> list[Frame]:
        jid = J1939Id.parse(can_id)
        if jid.pgn == PGN_REQUEST and len(data) >= 3:
            req = data[0] | data[1] << 8 | data[2] << 16
            if req == PGN_ADDRESS_CLAIMED and jid.da in (ADDR_GLOBAL, self.address):
                if self.state == ClaimState.CANNOT_CLAIM:
                    return [self._claim_frame(ADDR_NULL)]
                if self.state in (ClaimState.CLAIMED, ClaimState.WAIT_VETO):
                    return [self._claim_frame(self.address)]
            return []
        if jid.pgn != PGN_ADDRESS_CLAIMED or len(data) < 8:
            return []
        other = int.from_bytes(bytes(data[:8]), "little")
        if jid.sa != ADDR_NULL:
            self.others[jid.sa] = other
        if other == self.name.value:
            return []                                   # our own claim echoed
        if jid.sa != self.address or self.state not in (ClaimState.WAIT_VETO, ClaimState.CLAIMED):
            return []
        self.contests += 1
        if self.name.value < other:                     # we win: say so again
            return [self._claim_frame(self.address)]
        self.lost += 1
        if self.name.arbitrary_address_capable:
            nxt = self._next_free()
            if nxt is not None:
                self._tried.add(nxt)
                return self._claim(nxt, now_s)
        self.state = ClaimState.CANNOT_CLAIM
        self.address = ADDR_NULL
        return [self._claim_frame(ADDR_NULL)]


# ---- CRC ---------------------------------------------------------------------------------------
def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850: poly 0x1D, init 0xFF, final XOR 0xFF (check("123456789") == 0x4B)."""
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF
