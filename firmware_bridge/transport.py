"""A serial link that survives an unplugged adapter: reopen with backoff, count the outage.

The link owns the port object. Any thread whose read or write fails calls ``fail(port, error)``;
one thread (the sink's writer, or the monitor loop) calls ``try_connect()`` until the port is
back. A port that vanished and returns under the same name (USB adapter re-plugged, a udev
symlink re-pointed) is picked up again; the time without a port is the outage.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import serial

from acesplat.core.errors import InputError

Opener = Callable[[], serial.SerialBase]

READ_TIMEOUT_S = 0.05
"""Reader wake-up period: bounds how long close() waits for the reader thread."""
WRITE_TIMEOUT_S = 0.5
"""A write stuck this long (flow control, a peer that stopped reading) is abandoned, not waited on."""


def serial_opener(port: str, baud: int) -> Opener:
    """Open ``port`` (a device path or any pyserial URL such as ``loop://``) at ``baud``."""
    if baud <= 0:
        raise InputError(None, f"baud rate must be positive, got {baud}")

    def open_port() -> serial.SerialBase:
        return serial.serial_for_url(port, baudrate=baud, timeout=READ_TIMEOUT_S, write_timeout=WRITE_TIMEOUT_S)

    return open_port


class SerialLink:
    """Thread-safe holder of the current port, with reconnect backoff and outage accounting."""

    def __init__(
        self,
        opener: Opener,
        name: str | None = None,
        backoff_s: tuple[float, float] = (0.05, 2.0),
        clock: Callable[[], float] = time.monotonic,
        on_down: Callable[[], None] | None = None,
    ):
        self._opener = opener
        self.name = name
        self._on_down = on_down
        self._backoff = backoff_s
        self._clock = clock
        self._lock = threading.Lock()
        self._port: serial.SerialBase | None = None
        self._connected = threading.Event()
        self._delay = backoff_s[0]
        self._next_attempt = 0.0
        self._down_since: float | None = None
        self._outage_total = 0.0
        self._closed = False
        self.reconnects = 0
        self.last_error = ""

    def try_connect(self) -> bool:
        """Open the port if it is down and the backoff allows; True if connected afterwards."""
        now = self._clock()
        with self._lock:
            if self._closed:
                return False
            if self._port is not None:
                return True
            if now < self._next_attempt:
                return False
        try:
            port = self._opener()
        except (serial.SerialException, OSError, ValueError) as e:
            with self._lock:
                self.last_error = str(e)
                self._next_attempt = self._clock() + self._delay
                self._delay = min(self._delay * 2.0, self._backoff[1])
            return False
        with self._lock:
            if self._closed:  # close() ran while we were opening
                port.close()
                return False
            self._port = port
            self._delay = self._backoff[0]
            if self._down_since is not None:
                self._outage_total += self._clock() - self._down_since
                self._down_since = None
                self.reconnects += 1
            self._connected.set()
        return True

    def open_first(self) -> None:
        """The first open, synchronous: a wrong port name is bad input, not an outage to wait out."""
        if not self.try_connect():
            raise InputError(self.name, f"cannot open serial port ({self.last_error})")

    def seconds_until_retry(self) -> float:
        with self._lock:
            return max(0.0, self._next_attempt - self._clock())

    @property
    def port(self) -> serial.SerialBase | None:
        return self._port

    def wait_connected(self, timeout: float) -> serial.SerialBase | None:
        self._connected.wait(timeout)
        return self._port

    def fail(self, port: serial.SerialBase, error: BaseException | str) -> None:
        """Report that ``port`` failed; closes it once even if several threads report it."""
        with self._lock:
            if port is None or port is not self._port:
                return
            self._port = None
            self._connected.clear()
            self._down_since = self._clock()
            self._next_attempt = self._clock()
            self.last_error = str(error) or type(error).__name__
        try:
            port.close()
        except Exception:  # a vanished device may fail to close; it is gone either way
            pass
        if self._on_down is not None:
            self._on_down()

    def read(self, port: serial.SerialBase) -> bytes:
        """What ``port`` has received (waiting up to its read timeout); b"" and the link down if it failed."""
        try:
            return port.read(max(1, min(port.in_waiting, 4096)))
        except Exception as e:  # unplugged, or closed by another thread after a failed write
            self.fail(port, e)
            return b""

    def outage_s(self) -> float:
        """Seconds the port was lost after having been open, including an outage in progress."""
        with self._lock:
            ongoing = 0.0 if self._down_since is None else self._clock() - self._down_since
            return self._outage_total + ongoing

    def close(self) -> None:
        with self._lock:
            self._closed = True
            port, self._port = self._port, None
            if self._down_since is not None:
                self._outage_total += self._clock() - self._down_since
                self._down_since = None
            self._connected.set()  # wake waiters so they see the link is closed
        if port is not None:
            try:
                port.close()
            except Exception:
                pass
