"""A bounded ISO 15765-2 (ISO-TP) endpoint for the controller's diagnostic frames.

Normal addressing on classical CAN: every frame carries 8 bytes, the unused ones padded with
0xCC. No thread and no clock of its own: the caller passes its monotonic time ``now_s`` (s)
to every call, so the endpoint is pure and testable frame by frame.

Receive: a single frame (SF, 1..7 bytes) is a request at once; a first frame (FF, 8..4095
bytes) opens a reception into a preallocated 4095-byte buffer and queues a flow control
"continue to send" with BS = 0 (no further flow control) and STmin = 0; consecutive frames
(CF) must follow with sequence numbers 1, 2, … 15, 0, 1 … within N_Cr (1 s) of the previous
one. A wrong sequence number or a late CF aborts the reception (ISO 15765-2: the message is
lost, no answer). A FF longer than the buffer is answered with flow control "overflow".

Send: a message up to 4095 bytes goes out as one SF, or as a FF followed, after the peer's
flow control, by CFs: BS CFs per flow control (BS = 0: all of them), each released STmin
after the previous one. A flow control "wait" restarts N_Bs; "overflow", or no flow control
within N_Bs (1 s), aborts the transmission.

Frames to send collect in a queue: :meth:`IsoTpEndpoint.due` returns those whose release time
has come (the caller sends them); :attr:`IsoTpEndpoint.next_release_s` says when the next one
is due, so a caller waiting on its bus can wake up in time.
"""

from __future__ import annotations

from collections import deque

PADDING = 0xCC
FRAME_LEN = 8
MAX_MESSAGE = 4095  # the largest FF_DL of classical CAN without the 32-bit escape, bytes
N_CR_S = 1.0  # receiver: longest gap between consecutive frames, s
N_BS_S = 1.0  # sender: longest wait for a flow control, s

# protocol control information (PCI) types: the high nibble of byte 0
SF, FF, CF, FC = 0, 1, 2, 3
FC_CTS, FC_WAIT, FC_OVFLW = 0, 1, 2


def pad(frame: bytes | bytearray) -> bytes:
    """``frame`` padded to 8 bytes with 0xCC."""
    return bytes(frame) + bytes((PADDING,)) * (FRAME_LEN - len(frame))


def stmin_s(value: int) -> float:
    """The separation time STmin of a flow control byte, s (ISO 15765-2: 0x00..0x7F ms,
    0xF1..0xF9 100..900 µs; reserved values count as 127 ms)."""
    if value <= 0x7F:
        return value / 1000.0
    if 0xF1 <= value <= 0xF9:
        return (value - 0xF0) / 10000.0
    return 0.127


class IsoTpEndpoint:
    """One side of an ISO-TP link (see the module doc); all times in s on the caller's
    monotonic clock."""

    def __init__(self, *, max_message: int = MAX_MESSAGE, n_cr_s: float = N_CR_S,
                 n_bs_s: float = N_BS_S) -> None:
        if not 8 <= max_message <= MAX_MESSAGE:
            raise ValueError(f"max_message {max_message}: must be 8..{MAX_MESSAGE} bytes")
        self.max_message = max_message
        self.n_cr_s = n_cr_s
        self.n_bs_s = n_bs_s
        # reception: preallocated buffer, expected length (0 = idle), bytes so far
        self._rx = bytearray(max_message)
        self._rx_len = 0
        self._rx_got = 0
        self._rx_seq = 0
        self._rx_last_s = 0.0
        # transmission: the message, its next byte, next sequence number, CFs left in the
        # block (-1 = unlimited), waiting for a flow control since (None = not waiting)
        self._tx = b""
        self._tx_pos = 0
        self._tx_seq = 0
        self._tx_block_left = 0
        self._tx_stmin_s = 0.0
        self._fc_wait_since: float | None = None
        self._out: deque[tuple[float, bytes]] = deque()  # (release time s, 8-byte frame)
        self.counts = {"received": 0, "sent": 0, "aborted_rx": 0, "aborted_tx": 0,
                       "ignored": 0, "overflow": 0}

    # ------------------------------------------------------------------ state
    @property
    def receiving(self) -> bool:
        """A segmented message is being received."""
        return self._rx_len > 0

    @property
    def sending(self) -> bool:
        """A segmented message is being sent (frames still to queue or to release)."""
        return self._tx_pos < len(self._tx) or bool(self._out)

    @property
    def next_release_s(self) -> float | None:
        """When the next queued frame is due, s (None: nothing queued)."""
        return self._out[0][0] if self._out else None

    def due(self, now_s: float) -> list[bytes]:
        """The queued frames whose release time has come (in order); the caller sends them."""
        out: list[bytes] = []
        while self._out and self._out[0][0] <= now_s:
            out.append(self._out.popleft()[1])
        return out

    def reset(self) -> None:
        """Drop any reception, transmission and queued frame."""
        self._rx_len = self._rx_got = 0
        self._tx, self._tx_pos, self._fc_wait_since = b"", 0, None
        self._out.clear()

    def poll(self, now_s: float) -> None:
        """Apply the timeouts at ``now_s`` (s): N_Cr of a reception, N_Bs of a transmission
        waiting for a flow control."""
        if self._rx_len and now_s - self._rx_last_s > self.n_cr_s:
            self._abort_rx()
        if self._fc_wait_since is not None and now_s - self._fc_wait_since > self.n_bs_s:
            self._abort_tx()

    # ------------------------------------------------------------------ receive
    def feed(self, frame_data: bytes | bytearray, now_s: float) -> bytes | None:
        """Take one received frame at ``now_s`` (s); return a complete message, if this frame
        completes one. A flow control frame is consumed by the transmission side."""
        self.poll(now_s)
        if not frame_data:
            self.counts["ignored"] += 1
            return None
        kind = frame_data[0] >> 4
        if kind == SF:
            length = frame_data[0] & 0x0F
            if not 1 <= length <= min(7, len(frame_data) - 1):
                self.counts["ignored"] += 1  # SF_DL 0 is the CAN FD escape: not ours
                return None
            if self._rx_len:  # a new SF ends a reception in progress (ISO 15765-2)
                self._abort_rx()
            self.counts["received"] += 1
            return bytes(frame_data[1:1 + length])
        if kind == FF:
            return self._first_frame(frame_data, now_s)
        if kind == CF:
            return self._consecutive_frame(frame_data, now_s)
        if kind == FC:
            self._flow_control(frame_data, now_s)
            return None
        self.counts["ignored"] += 1
        return None

    def _first_frame(self, data: bytes | bytearray, now_s: float) -> None:
        if len(data) < FRAME_LEN:
            self.counts["ignored"] += 1
            return None
        length = ((data[0] & 0x0F) << 8) | data[1]
        if self._rx_len:  # a new FF ends a reception in progress (ISO 15765-2)
            self._abort_rx()
        if length == 0 or length > self.max_message:  # 0: the 32-bit escape, too long anyway
            self.counts["overflow"] += 1
            self._out.append((now_s, pad(bytes((FC << 4 | FC_OVFLW, 0, 0)))))
            return None
        if length < FRAME_LEN:  # would have fitted a SF: invalid, ignored
            self.counts["ignored"] += 1
            return None
        self._rx[:6] = data[2:8]
        self._rx_len, self._rx_got, self._rx_seq, self._rx_last_s = length, 6, 1, now_s
        self._out.append((now_s, pad(bytes((FC << 4 | FC_CTS, 0, 0)))))  # BS 0, STmin 0
        return None

    def _consecutive_frame(self, data: bytes | bytearray, now_s: float) -> bytes | None:
        if not self._rx_len:
            self.counts["ignored"] += 1  # no reception open: not for us
            return None
        if (data[0] & 0x0F) != self._rx_seq:
            self._abort_rx()
            return None
        take = min(len(data) - 1, self._rx_len - self._rx_got)
        self._rx[self._rx_got:self._rx_got + take] = data[1:1 + take]
        self._rx_got += take
        self._rx_seq = (self._rx_seq + 1) & 0x0F
        self._rx_last_s = now_s
        if self._rx_got < self._rx_len:
            return None
        message = bytes(self._rx[:self._rx_len])
        self._rx_len = self._rx_got = 0
        self.counts["received"] += 1
        return message

    def _abort_rx(self) -> None:
        self._rx_len = self._rx_got = 0
        self.counts["aborted_rx"] += 1

    # ------------------------------------------------------------------ send
    def send(self, message: bytes, now_s: float) -> None:
        """Queue ``message`` (1..max_message bytes) at ``now_s`` (s); a transmission still in
        progress is abandoned (the newer answer wins)."""
        if not 1 <= len(message) <= self.max_message:
            raise ValueError(f"ISO-TP message of {len(message)} bytes: must be "
                             f"1..{self.max_message}")
        if self.sending:
            self._abort_tx()
        if len(message) <= 7:
            self._out.append((now_s, pad(bytes((len(message),)) + message)))
            self.counts["sent"] += 1
            return
        self._tx, self._tx_pos, self._tx_seq = bytes(message), 6, 1
        self._out.append((now_s, bytes((FF << 4 | len(message) >> 8, len(message) & 0xFF))
                          + self._tx[:6]))
        self._fc_wait_since = now_s

    def _flow_control(self, data: bytes | bytearray, now_s: float) -> None:
        if self._fc_wait_since is None or len(data) < 3:
            self.counts["ignored"] += 1  # not expecting one
            return
        status = data[0] & 0x0F
        if status == FC_WAIT:
            self._fc_wait_since = now_s
            return
        if status != FC_CTS:  # overflow or invalid flow status: abort (ISO 15765-2)
            self._abort_tx()
            return
        self._fc_wait_since = None
        self._tx_block_left = data[1] or -1
        self._tx_stmin_s = stmin_s(data[2])
        release = now_s
        while self._tx_pos < len(self._tx) and self._tx_block_left != 0:
            chunk = self._tx[self._tx_pos:self._tx_pos + 7]
            self._out.append((release, pad(bytes((CF << 4 | self._tx_seq,)) + chunk)))
            self._tx_pos += len(chunk)
            self._tx_seq = (self._tx_seq + 1) & 0x0F
            self._tx_block_left -= 1
            release += self._tx_stmin_s
        if self._tx_pos >= len(self._tx):
            self._tx, self._tx_pos = b"", 0
            self.counts["sent"] += 1
        else:  # block done: the peer's next flow control releases the next block
            self._fc_wait_since = now_s

    def _abort_tx(self) -> None:
        self._tx, self._tx_pos, self._fc_wait_since = b"", 0, None
        self._out.clear()
        self.counts["aborted_tx"] += 1
