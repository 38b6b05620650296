"""Links from the streamer to a device: UDP, serial (pyserial) and a dry-run file.

`Transport.open(url)` understands ``udp://HOST:PORT``, ``serial://DEVICE?baud=115200``
(any pyserial URL such as ``loop://`` works too) and ``file://PATH`` (dry run:
frames are appended to PATH in the byte-stream format, nothing comes back).
Every failure of the link raises `TransportError`, which the streamer turns
into a stop and a report.
"""

from __future__ import annotations

import abc
import socket
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import serial

from crtraj.core.errors import InputError
from crtraj.hardware.protocol import StreamDecoder, stream_encode


class TransportError(RuntimeError):
    """The link failed (socket error, serial error, disk full): streaming must stop."""


class LinkLostError(TransportError):
    """The link itself is gone (a USB-serial adapter unplugged, its device node removed): nothing more can be
    sent or read on it; the streamer reports status ``link_lost``."""


def parse_hostport(text: str, what: str) -> tuple[str, int]:
    """Split ``HOST:PORT``; `InputError` naming `what` when malformed."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise InputError(f"{what}: expected HOST:PORT, got {text!r}")
    if not (port.isascii() and port.isdecimal()):  # int() also takes other scripts' digits and "_"
        raise InputError(f"{what}: port must be an integer, got {port!r}")
    p = int(port)
    if not 0 <= p <= 65535:
        raise InputError(f"{what}: port must be in 0..65535, got {p}")
    return host, p


class Transport(abc.ABC):
    """A bidirectional frame link. Subclasses implement `send`, `receive` and `close`.

    has_telemetry: False for links that never answer (dry run); the streamer
    then disables its telemetry watchdog.
    """

    has_telemetry = True
    description = "transport"

    @abc.abstractmethod
    def send(self, frame: bytes) -> None:
        """Send one encoded frame."""

    @abc.abstractmethod
    def receive(self) -> list[bytes]:
        """Every frame received since the last call (never blocks)."""

    def close(self) -> None:  # noqa: B027 - links with nothing to release keep this default
        """Release the link (idempotent)."""

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @staticmethod
    def open(url: str, *, baud: int = 115200) -> Transport:
        """Open ``udp://HOST:PORT``, ``serial://DEV[?baud=N]`` or ``file://PATH``."""
        parts = urlsplit(url)
        if parts.scheme == "udp":
            host, port = parse_hostport(parts.netloc, "--udp")
            return _UdpTransport(host, port)
        if parts.scheme == "serial":
            dev = parts.netloc + parts.path
            q = parse_qs(parts.query)
            b = int(q["baud"][0]) if "baud" in q else baud
            return _SerialTransport(dev, b)
        if parts.scheme == "file":
            return _FileTransport(parts.netloc + parts.path)
        if parts.scheme == "dynamixel":  # needs the servo ids and tick scales: crtraj.hardware.dynamixel._link
            raise InputError(f"{url}: a Dynamixel bus opens with Streamer.open(url, actuators) (it needs the ids)")
        raise InputError(
            f"stream target: unknown scheme in {url!r} (use udp://HOST:PORT, serial://DEV, dynamixel://DEV or "
            "file://PATH)"
        )


class _UdpTransport(Transport):
    """One frame per datagram to HOST:PORT; telemetry is read from the same (connected) socket."""

    def __init__(self, host: str, port: int) -> None:
        if port == 0:
            raise InputError("--udp: port 0 is not a device address")
        try:
            infos = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
        except OSError as exc:
            raise InputError(f"--udp: cannot resolve {host!r} ({exc})") from None
        addr = infos[0][4]
        self.description = f"udp://{addr[0]}:{addr[1]}"
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if addr[0].startswith("127."):
                self._sock.bind(("127.0.0.1", 0))
            # connect(): only the device's datagrams are delivered, and ICMP
            # "port unreachable" surfaces as an error instead of silence
            self._sock.connect(addr)
            self._sock.setblocking(False)
        except OSError as exc:
            self._sock.close()
            raise TransportError(f"{self.description}: {exc}") from None

    def send(self, frame: bytes) -> None:
        try:
            self._sock.send(frame)
        except BlockingIOError:
            raise TransportError(f"{self.description}: send buffer full") from None
        except OSError as exc:
            raise TransportError(f"{self.description}: {exc}") from None

    def receive(self) -> list[bytes]:
        out = []
        while True:
            try:
                out.append(self._sock.recv(65536))
            except BlockingIOError:
                return out
            except OSError as exc:
                raise TransportError(f"{self.description}: {exc}") from None

    def close(self) -> None:
        self._sock.close()


class _SerialTransport(Transport):
    """COBS-framed frames over a serial port (pyserial; ``loop://`` for a loopback)."""

    def __init__(self, device: str, baud: int = 115200) -> None:

        if baud <= 0:
            raise InputError(f"--baud: must be > 0, got {baud}")
        self.description = f"serial://{device}?baud={baud}"
        try:
            self._port = serial.serial_for_url(device, baudrate=baud, timeout=0, write_timeout=0.05)
        except (serial.SerialException, ValueError) as exc:
            raise TransportError(f"{self.description}: {exc}") from None
        self._serial = serial
        self._dec = StreamDecoder()

    @property
    def decode_errors(self) -> int:
        return self._dec.errors

    def send(self, frame: bytes) -> None:
        try:
            self._port.write(stream_encode(frame))
        except (self._serial.SerialException, OSError) as exc:
            raise TransportError(f"{self.description}: {exc}") from None

    def receive(self) -> list[bytes]:
        try:
            n = self._port.in_waiting
            data = self._port.read(n) if n else b""
        except (self._serial.SerialException, OSError) as exc:
            raise TransportError(f"{self.description}: {exc}") from None
        return self._dec.feed(data) if data else []

    def close(self) -> None:
        self._port.close()


class _FileTransport(Transport):
    """Dry run: frames go to a file in the byte-stream format (COBS + 0x00); nothing comes back."""

    has_telemetry = False

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.description = f"file://{self.path}"
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("wb")
        except OSError as exc:
            raise InputError(f"--dry-run: cannot write {self.path} ({exc.strerror})") from None

    def send(self, frame: bytes) -> None:
        try:
            self._fh.write(stream_encode(frame))
            self._fh.flush()
        except (OSError, ValueError) as exc:
            raise TransportError(f"{self.description}: {exc}") from None

    def receive(self) -> list[bytes]:
        return []

    def close(self) -> None:
        self._fh.close()
