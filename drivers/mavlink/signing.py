"""MAVLink2 message signing: the secret key's source and the check of incoming signatures.

Wire format (MAVLink2, incompat flag 0x01): the frame ends with a 13-byte signature block
``link_id (u8) | timestamp (u48 LE, 10 us units since 2015-01-01 00:00 UTC) | sig (6 B)`` where
``sig = sha256(key || frame[:-6])[:6]``; ``frame[:-6]`` is header, payload, CRC, link id and
timestamp. A stream is ``(link_id, sysid, compid)``; its timestamps must strictly increase.

The key is 32 bytes. It never comes from the session YAML: :func:`load_signing_key` reads it
from a file or an environment variable (default ``FASTHEX_MAVLINK_KEY``). Either holds 64 hex
digits (the key itself) or a passphrase, whose SHA-256 is the key (MAVProxy's ``signing key
PASSPHRASE`` convention, so a lab can type the same passphrase into MAVProxy); a file may also
hold the 32 raw bytes.

Why we verify ourselves instead of pymavlink's ``setup_signing`` (2.4.50):

* its ``allow_unsigned_callback`` also accepts *badly signed* messages of an allowed ID; here
  the allow-list only ever applies to unsigned frames;
* it records a new stream's timestamp before checking the signature, so one forged frame with a
  far-future timestamp makes every genuine frame of that stream look replayed; here the MAC is
  checked first and only a valid frame moves the stream's timestamp;
* it counts wrong keys and replays together; here they are counted apart, and a frame more
  than a minute behind our clock is counted as stale.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import logging
import os
import stat
import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from drivers.errors import DriverError

log = logging.getLogger(__name__)

DEFAULT_KEY_ENV = "FASTHEX_MAVLINK_KEY"
KEY_LEN = 32
SIGNATURE_BLOCK_LEN = 13
MAVLINK2_MAGIC = 0xFD
IFLAG_SIGNED = 0x01
#: Seconds between the Unix epoch and the MAVLink signing epoch (2015-01-01 00:00 UTC).
SIGNING_EPOCH_UNIX_S = 1_420_070_400
#: A frame may be at most this far (10 us units: one minute) behind our timestamp; older ones
#: are stale (MAVLink's rule for new streams, applied to every frame: a captured frame cannot
#: be played back a minute later on a stream that has been quiet since).
NEW_STREAM_WINDOW = 6_000_000


class SigningKeyError(DriverError):
    """The signing key cannot be read or has the wrong form; ``device`` names its source."""


def key_from_text(text: str) -> bytes:
    """The 32-byte key from 64 hex digits, or SHA-256 of a passphrase."""
    s = text.strip()
    if not s:
        raise ValueError("empty key text")
    if len(s) == 2 * KEY_LEN:
        try:
            return bytes.fromhex(s)
        except ValueError:
            pass
    return hashlib.sha256(s.encode("utf-8")).digest()


def load_signing_key(key_file: str | os.PathLike[str] | None = None,
                     env_var: str | None = DEFAULT_KEY_ENV,
                     environ: Mapping[str, str] | None = None) -> bytes | None:
    """The signing key from ``key_file`` if given, else from ``env_var``; None if neither.

    Raises :class:`SigningKeyError` naming the file or variable when it is unreadable or empty.
    A key file readable by group or others is accepted with a warning.
    """
    env: Mapping[str, str] = os.environ if environ is None else environ
    if key_file is not None:
        path = Path(key_file)
        try:
            data = path.read_bytes()
            mode = path.stat().st_mode
        except OSError as exc:
            raise SigningKeyError(str(path), f"cannot read signing key: {exc.strerror}") from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            log.warning("%s: signing key file is readable by others (chmod 600 it)", path)
        if len(data) == KEY_LEN:
            try:
                text = data.decode("ascii")
            except UnicodeDecodeError:
                return data  # 32 raw bytes
            if not text.isprintable():
                return data
        try:
            return key_from_text(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            raise SigningKeyError(str(path), "signing key file is empty or not text") from None
    if env_var is not None and env_var in env:
        try:
            return key_from_text(env[env_var])
        except ValueError:
            raise SigningKeyError(f"${env_var}", "signing key variable is empty") from None
    return None


def signing_timestamp_now(unix_time_s: float | None = None) -> int:
    """The current signing timestamp (10 us units since 2015-01-01 UTC)."""
    t = time.time() if unix_time_s is None else unix_time_s
    return max(0, int((t - SIGNING_EPOCH_UNIX_S) * 100_000))


class Verdict(enum.Enum):
    GOOD = "good"  # signed with our key, fresh timestamp
    UNSIGNED = "unsigned"  # MAVLink1, or MAVLink2 without the signed flag
    BAD_SIGNATURE = "bad_signature"  # wrong key, or corrupted
    REPLAY = "replay"  # right key, timestamp not newer than the stream's last
    STALE = "stale"  # right key, timestamp more than the window behind our clock


@dataclass(frozen=True, slots=True)
class SigningStats:
    good: int
    unsigned_allowed: int  # unsigned, accepted through the allow-list
    unsigned_rejected: int
    bad_signature: int
    replayed: int
    stale: int = 0

    @property
    def rejected(self) -> int:
        return self.unsigned_rejected + self.bad_signature + self.replayed + self.stale


_TS = struct.Struct("<IH")


def frame_signature(key: bytes, frame_without_sig: bytes) -> bytes:
    """The 6-byte signature of a MAVLink2 frame (everything up to the signature itself)."""
    return hashlib.sha256(key + frame_without_sig).digest()[:6]


class SignatureVerifier:
    """Checks incoming MAVLink2 frames against one key; keeps per-stream timestamps.

    Not thread-safe: owned by the bridge's service thread. ``unix_time`` is injectable so that
    tests and lockstep runs control the new-stream window.
    """

    def __init__(self, key: bytes, allow_unsigned: frozenset[int] = frozenset(),
                 unix_time: Callable[[], float] = time.time) -> None:
        if len(key) != KEY_LEN:
            raise ValueError(f"signing key must be {KEY_LEN} bytes, got {len(key)}")
        self._key = key
        self.allow_unsigned = allow_unsigned
        self._unix_time = unix_time
        self._streams: dict[tuple[int, int, int], int] = {}
        self._newest = 0
        self.good = 0
        self.unsigned_allowed = 0
        self.unsigned_rejected = 0
        self.bad_signature = 0
        self.replayed = 0
        self.stale = 0

    @property
    def newest_timestamp(self) -> int:
        """The newest timestamp seen on any good frame (outgoing signing stays above it)."""
        return self._newest

    def stats(self) -> SigningStats:
        return SigningStats(self.good, self.unsigned_allowed, self.unsigned_rejected,
                            self.bad_signature, self.replayed, self.stale)

    def classify(self, frame: bytes) -> Verdict:
        """The verdict on one complete frame (no counters, no state change)."""
        return self._check(frame, commit=False)

    def accept(self, frame: bytes, msg_id: int) -> bool:
        """Check ``frame`` (a complete MAVLink frame with message id ``msg_id``), update the
        counters and the stream timestamp; True if the message may be acted upon."""
        verdict = self._check(frame, commit=True)
        if verdict is Verdict.GOOD:
            self.good += 1
            return True
        if verdict is Verdict.UNSIGNED:
            if msg_id in self.allow_unsigned:
                self.unsigned_allowed += 1
                return True
            self.unsigned_rejected += 1
        elif verdict is Verdict.BAD_SIGNATURE:
            self.bad_signature += 1
        elif verdict is Verdict.STALE:
            self.stale += 1
        else:
            self.replayed += 1
        return False

    def _check(self, frame: bytes, *, commit: bool) -> Verdict:
        if (len(frame) < 10 + 2 + SIGNATURE_BLOCK_LEN or frame[0] != MAVLINK2_MAGIC
                or not frame[2] & IFLAG_SIGNED):
            return Verdict.UNSIGNED
        body, sig = frame[:-6], frame[-6:]
        if not hmac.compare_digest(frame_signature(self._key, bytes(body)), bytes(sig)):
            return Verdict.BAD_SIGNATURE
        link_id = frame[-13]
        lo, hi = _TS.unpack_from(frame, len(frame) - 12)
        timestamp = lo | (hi << 32)
        stream = (link_id, frame[5], frame[6])
        last = self._streams.get(stream)
        if last is not None and timestamp <= last:
            return Verdict.REPLAY
        now = max(self._newest, signing_timestamp_now(self._unix_time()))
        if timestamp + NEW_STREAM_WINDOW < now:
            return Verdict.STALE
        if commit:
            self._streams[stream] = timestamp
            self._newest = max(self._newest, timestamp)
        return Verdict.GOOD
