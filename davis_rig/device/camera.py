"""The DAVIS346 camera: open, configure, start/stop, and iterate over decoded data.

Typical use (libcaer's client flow, PROTOCOL.md §7.3)::

    with Davis346.open() as cam:                 # or Davis346.open(backend=VirtualDavis346Backend(...))
        cam.send_default_config()
        cam.set_exposure(8000)
        cam.add_raw_listener(journal.write)      # optional: keep the raw USB bytes
        cam.start()
        for chunk in cam.chunks(timeout_s=1.0):  # DecodedChunk per read (one or more USB transfers)
            ...
        cam.stop()

The camera object owns a :class:`~davis_rig.usb.transport.UsbTransport` (control + bulk), a
:class:`~davis_rig.device.reader.RingReader` (asynchronous transfers in flight; a
:class:`~davis_rig.device.reader.TransferReader` thread on backends without them) while started, a fresh
:class:`~davis_rig.protocol.decoder.StreamDecoder` per start (libcaer resets its parsers at ``dataStart``), and on
FX3 boards a :class:`~davis_rig.device.debug.DebugReader` on the debug endpoint from open to close.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from davis_rig.device.debug import DebugMessage, DebugReader
from davis_rig.device.info import DeviceInfo, read_device_info
from davis_rig.device.reader import (
    DEFAULT_QUEUE_TRANSFERS,
    DEFAULT_READ_BYTES,
    DEFAULT_READ_TIMEOUT_MS,
    RingReader,
    TransferQueue,
    TransferReader,
)
from davis_rig.errors import DeviceDisconnectedError, DeviceError, TransportError
from davis_rig.protocol.biases import DAVIS346_DEFAULT_BIASES, Bias, BiasEntry, bias_param, check_bias_for, decode_bias
from davis_rig.protocol.config import (
    DAVIS_FX3_PID,
    DEBUG_ENDPOINT,
    Aps,
    Dvs,
    Imu,
    Module,
    Mux,
    exposure_write,
    frame_interval_write,
)
from davis_rig.protocol.decoder import DecodedChunk, DecoderStats, StreamDecoder
from davis_rig.protocol.sequences import (
    DEFAULT_EXPOSURE_US,
    DEFAULT_FRAME_INTERVAL_US,
    ClearHalt,
    aps_snapshot_pulse,
    default_config_sequence,
    global_shutter_writes,
    start_sequence,
    stop_sequence,
    timestamp_reset_pulse,
)
from davis_rig.usb.async_bulk import DEFAULT_TRANSFER_BYTES, DEFAULT_TRANSFERS
from davis_rig.usb.transport import UsbTransport, run_config_steps


#: Default upper bound of bytes decoded per :meth:`Davis346.read` call.
DEFAULT_BATCH_BYTES = 1 << 20


@dataclass(frozen=True)
class CameraStats:
    """Acquisition counters since the last :meth:`Davis346.start`.

    Attributes:
        transfers: USB reads that returned data.
        bytes: bytes received.
        dropped_transfers: reads dropped because the consumer fell behind (data lost).
        dropped_bytes: bytes in those reads.
        timeouts: reads that timed out without data (idle, not an error).
        stalls: endpoint stalls cleared by the transport.
        decoded_transfers: transfers handed to the decoder (and raw listeners).
        decoder: the decoder's cumulative counters.
    """

    transfers: int
    bytes: int
    dropped_transfers: int
    dropped_bytes: int
    timeouts: int
    stalls: int
    decoded_transfers: int
    decoder: DecoderStats


class Davis346:
    """An open DAVIS346 (context manager). Use :meth:`open`; the constructor only stores its arguments.

    Args:
        transport: an open transport.
        info: what the device reported at open.
        sleep: ``sleep(seconds)`` used for the documented waits of start (10 + 200 + 50 ms); tests inject one.
        batch_bytes: :meth:`read` decodes the next transfer plus any already queued behind it, up to this many
            bytes, in one decoder call (about 2× cheaper than one call per transfer); 0 = one transfer per read.
        usb_transfers: asynchronous bulk transfers kept in flight (libcaer: 8); 0, or a pyusb backend without
            libusb's asynchronous API, = a thread of synchronous reads instead (see :mod:`davis_rig.device.reader`).
        read_bytes: bytes per USB transfer (default 32 KiB) or per synchronous read (default 128 KiB).
        read_timeout_ms: per-read timeout of synchronous reads, ms.
        queue_transfers: reader queue depth (transfers) before transfers are dropped (default: 64 MiB nominal,
            i.e. 512 synchronous reads or 2048 ring transfers of 32 KiB).
    """

    def __init__(
        self,
        transport: UsbTransport,
        info: DeviceInfo,
        *,
        sleep: Callable[[float], Any] = time.sleep,
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        usb_transfers: int = DEFAULT_TRANSFERS,
        read_bytes: int | None = None,
        read_timeout_ms: int = DEFAULT_READ_TIMEOUT_MS,
        queue_transfers: int | None = None,
    ):
        self.transport = transport
        self.info = info
        self._sleep = sleep
        self._batch_bytes = int(batch_bytes)
        self._usb_transfers = int(usb_transfers)
        self._read_bytes = read_bytes
        self._read_timeout_ms = read_timeout_ms
        self._queue_transfers = queue_transfers
        self._biases: dict[str, Bias] = {e.name: e.bias for e in DAVIS346_DEFAULT_BIASES}
        self._exposure_us = DEFAULT_EXPOSURE_US
        self._frame_interval_us = DEFAULT_FRAME_INTERVAL_US
        self._global_shutter = info.features.aps_has_global_shutter
        self._producers = {"dvs": True, "aps": True, "imu": True, "extinput": True}  # libcaer's (and DV's) default
        self._listeners: list[Callable[[bytes], Any]] = []
        self._reader: TransferQueue | None = None
        self._debug_reader: DebugReader | None = None
        self._decoder: StreamDecoder | None = None
        self._decoded_transfers = 0
        self._running = False
        self._closed = False
        self._consumer_lock = threading.Lock()

    # --- opening / closing ----------------------------------------------------------------------
    @classmethod
    def open(
        cls,
        serial: str | None = None,
        backend: Any = None,
        *,
        sleep: Callable[[float], Any] = time.sleep,
        **reader_options: int,
    ) -> "Davis346":
        """Open a DAVIS346 over USB and read its description (§5).

        Args:
            serial: serial number; ``None`` = the first DAVIS that opens.
            backend: pyusb backend (``None`` = libusb-1.0; pass a ``VirtualDavis346Backend`` for tests).
            sleep: sleep function for the start waits.
            **reader_options: ``batch_bytes``, ``usb_transfers``, ``read_bytes``, ``read_timeout_ms``,
                ``queue_transfers``.

        Returns:
            The open camera.

        Raises:
            DeviceNotFoundError, DevicePermissionError, DeviceBusyError, DeviceVersionError, TransportError:
                see :meth:`UsbTransport.open`.
        """
        transport = UsbTransport.open(serial=serial, backend=backend)
        try:
            info = read_device_info(transport)
        except BaseException:
            transport.close()
            raise
        camera = cls(transport, info, sleep=sleep, **reader_options)
        try:
            camera._listen_to_debug_endpoint()
        except BaseException:
            transport.close()
            raise
        return camera

    def _listen_to_debug_endpoint(self) -> None:
        """Read the FX3 debug endpoint from open to close, as libcaer does (FX2 boards have none)."""
        if self.info.product_id != DAVIS_FX3_PID:
            return
        api = self.transport.async_transfers() if self._usb_transfers > 0 else None
        self._debug_reader = DebugReader(
            self.transport.read_debug,
            api=api,
            clear_halt=lambda: self.transport.clear_halt(DEBUG_ENDPOINT),
            describe=f"DAVIS {self.info.serial}",
        ).start()

    def close(self) -> None:
        """Stop acquisition if running, stop reading the debug endpoint and release the USB device (idempotent,
        safe after an unplug)."""
        if self._closed:
            return
        try:
            self.stop()
        finally:
            self._closed = True
            if self._debug_reader is not None:
                self._debug_reader.stop()
            self.transport.close()

    def __enter__(self) -> "Davis346":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- configuration --------------------------------------------------------------------------
    def _steps(self, steps) -> None:
        run_config_steps(self.transport, steps, self._sleep)

    def send_default_config(self) -> None:
        """Send libcaer's default configuration: biases, chip, FPGA, USB (§6); resets the tracked settings.

        Raises:
            DeviceError: the chip is not a DAVIS346 (the bias table here is the DAVIS346 one).
        """
        if not self.info.is_davis346:
            raise DeviceError(
                f"DAVIS {self.info.serial}: chip id {self.info.chip_id} is not a DAVIS346 (expected 4, 5 or 9); "
                "its default biases are not implemented"
            )
        self._biases = {e.name: e.bias for e in DAVIS346_DEFAULT_BIASES}
        self._exposure_us = DEFAULT_EXPOSURE_US
        self._frame_interval_us = DEFAULT_FRAME_INTERVAL_US
        self._global_shutter = self.info.features.aps_has_global_shutter
        self._steps(
            default_config_sequence(
                dvs_size_xy=self.info.dvs_size_xy,
                aps_size_xy=self.info.aps_size_xy,
                features=self.info.features,
                clocks=self.info.clocks,
                imu_type=self.info.layout.imu_type,
            )
        )

    @property
    def biases(self) -> dict[str, Bias]:
        """The bias values last sent (or libcaer's defaults before any), name → bias (a copy)."""
        return dict(self._biases)

    def set_bias(self, name: str, bias: Bias | int) -> None:
        """Write one bias.

        Args:
            name: DAVIS346 bias name, e.g. ``"ONBN"`` (case-insensitive).
            bias: a bias object of the register's kind, or a raw register value.

        Raises:
            ProtocolError: unknown name, wrong bias kind or invalid raw value.
        """
        param = bias_param(name)
        if isinstance(bias, int) and not isinstance(bias, bool):
            bias = decode_bias(param, bias)
        check_bias_for(param, bias)
        self.transport.config_write(Module.BIAS, param, bias.encode())
        self._biases[name.upper()] = bias

    def set_biases(self, entries: list[BiasEntry] | dict[str, Bias]) -> None:
        """Write several biases (a ``{name: bias}`` dict or ``BiasEntry`` list), in order."""
        items = entries.items() if isinstance(entries, dict) else ((e.name, e.bias) for e in entries)
        for name, bias in items:
            self.set_bias(name, bias)

    @property
    def exposure_us(self) -> int:
        """APS exposure last set, µs."""
        return self._exposure_us

    def set_exposure(self, exposure_us: int) -> None:
        """Set the APS exposure (sent in ADC-clock cycles).

        Args:
            exposure_us: exposure, µs, 0..4194303.

        Raises:
            ProtocolError: out of range.
        """
        write = exposure_write(int(exposure_us), self.info.clocks)
        self.transport.config_write(*write)
        self._exposure_us = int(exposure_us)

    @property
    def frame_interval_us(self) -> int:
        """APS frame interval last set, µs."""
        return self._frame_interval_us

    def set_frame_interval(self, frame_interval_us: int) -> None:
        """Set the time between APS frame starts (sent in ADC-clock cycles).

        Args:
            frame_interval_us: interval, µs, 0..8388607.

        Raises:
            ProtocolError: out of range.
        """
        write = frame_interval_write(int(frame_interval_us), self.info.clocks)
        self.transport.config_write(*write)
        self._frame_interval_us = int(frame_interval_us)

    def set_global_shutter(self, enabled: bool) -> None:
        """Switch APS global/rolling shutter (CHIP 142 then APS 7).

        Raises:
            DeviceError: the sensor has no global shutter.
        """
        if not self.info.features.aps_has_global_shutter:
            raise DeviceError(f"DAVIS {self.info.serial}: this sensor has no global shutter")
        self._steps(global_shutter_writes(bool(enabled), self.info.features))
        self._global_shutter = bool(enabled)

    def _set_producer(self, name: str, enabled: bool, writes: list[tuple[int, int]]) -> None:
        self._producers[name] = bool(enabled)
        if self._running:
            for module, param in writes:
                self.transport.config_write(module, param, int(bool(enabled)))

    def set_dvs_enabled(self, enabled: bool) -> None:
        """Enable/disable DVS events (applied now if running, else at :meth:`start`)."""
        self._set_producer("dvs", enabled, [(Module.DVS, Dvs.RUN)])

    def set_aps_enabled(self, enabled: bool) -> None:
        """Enable/disable APS frames (applied now if running, else at :meth:`start`)."""
        self._set_producer("aps", enabled, [(Module.APS, Aps.RUN)])

    def set_imu_enabled(self, enabled: bool) -> None:
        """Enable/disable the IMU: accelerometer, gyroscope, temperature (on by default, like libcaer and DV; applied
        now if running, else at start)."""
        self._set_producer(
            "imu", enabled, [(Module.IMU, Imu.RUN_ACCELEROMETER), (Module.IMU, Imu.RUN_GYROSCOPE), (Module.IMU, Imu.RUN_TEMPERATURE)]
        )

    @property
    def producers(self) -> dict[str, bool]:
        """Which producers start() enables: ``{"dvs", "aps", "imu", "extinput"}`` → bool (a copy)."""
        return dict(self._producers)

    def timestamp_reset(self) -> None:
        """Pulse MUX TIMESTAMP_RESET (one 0xC2 request, set then clear)."""
        self._steps([timestamp_reset_pulse()])

    def snapshot(self) -> None:
        """Request one APS frame (APS RUN pulse, one 0xC2 request)."""
        self._steps([aps_snapshot_pulse()])

    def fpga_statistics(self) -> dict[str, int]:
        """The FPGA's 64-bit statistics counters the device has (empty if it reports none).

        ``mux_dvs_dropped`` / ``mux_extinput_dropped`` count events the FPGA dropped because USB stalled
        (DROP_*_ON_TRANSFER_STALL, on by default) — data lost before it ever reached the host; ``dvs_*`` are the
        DVS module's transaction and filter counters.

        Returns:
            ``{name: count}``.

        Raises:
            TransportError / DeviceDisconnectedError: USB failure.
        """
        f = self.info.features
        wanted = []
        if f.mux_has_statistics:
            wanted += [("mux_extinput_dropped", Module.MUX, Mux.STATISTICS_EXTINPUT_DROPPED),
                       ("mux_dvs_dropped", Module.MUX, Mux.STATISTICS_DVS_DROPPED)]
        if f.dvs_has_statistics:
            wanted += [("dvs_events_row", Module.DVS, Dvs.STATISTICS_EVENTS_ROW),
                       ("dvs_events_column", Module.DVS, Dvs.STATISTICS_EVENTS_COLUMN),
                       ("dvs_events_dropped", Module.DVS, Dvs.STATISTICS_EVENTS_DROPPED)]
            if f.dvs_has_pixel_filter:
                wanted.append(("dvs_filtered_pixels", Module.DVS, Dvs.STATISTICS_FILTERED_PIXELS))
            if f.dvs_has_background_activity_filter:
                wanted += [("dvs_filtered_background_activity", Module.DVS, Dvs.STATISTICS_FILTERED_BACKGROUND_ACTIVITY),
                           ("dvs_filtered_refractory_period", Module.DVS, Dvs.STATISTICS_FILTERED_REFRACTORY_PERIOD)]
        return {name: self.transport.config_read_u64(module, param) for name, module, param in wanted}

    # --- acquisition ----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """Whether :meth:`start` ran and :meth:`stop` did not (and the device did not vanish)."""
        return self._running

    def start(self) -> None:
        """Start streaming: libcaer's ``davisDataStart`` sequence (§7.1), with the reader thread started
        right after the endpoint halt is cleared (where libcaer submits its transfers).

        Raises:
            DeviceError: already running or closed.
            TransportError / DeviceDisconnectedError: USB failure (the stop sequence is sent as far as the device
                still answers, so the FPGA does not keep streaming, and the reader is stopped again).
        """
        if self._closed:
            raise DeviceError(f"DAVIS {self.info.serial}: camera is closed")
        if self._running:
            raise DeviceError(f"DAVIS {self.info.serial}: already started")
        self._decoder = StreamDecoder(self.info.layout)
        self._decoded_transfers = 0
        self._reader = self._make_reader()
        steps = start_sequence(**self._producers)
        try:
            for step in steps:
                self._steps([step])
                if isinstance(step, ClearHalt):
                    self._reader.start()
        except BaseException:
            self._abort_start()
            raise
        self._running = True

    def _abort_start(self) -> None:
        """Undo a failed :meth:`start`: best-effort stop sequence, then stop the readers.

        The failure may come after RUN_CHIP / USB RUN / MUX RUN were switched on; ``_running`` is still false,
        so a later :meth:`stop` / :meth:`close` would not switch them off. A transport error while stopping is
        ignored: the caller gets the error of the start.
        """
        try:
            if not self.transport.disconnected:
                self._steps(stop_sequence())
        except TransportError:
            pass  # the device no longer answers: nothing more to switch off from here
        finally:
            self._reader.stop()

    def _make_reader(self) -> TransferQueue:
        """A ring of asynchronous transfers where the backend has libusb's asynchronous API, else a read thread."""
        api = self.transport.async_transfers() if self._usb_transfers > 0 else None
        if api is None:
            return TransferReader(
                self.transport.read_data,
                read_bytes=self._read_bytes or DEFAULT_READ_BYTES,
                timeout_ms=self._read_timeout_ms,
                queue_transfers=self._queue_transfers or DEFAULT_QUEUE_TRANSFERS,
            )
        return RingReader(
            api,
            self.transport.clear_halt,
            transfers=self._usb_transfers,
            transfer_bytes=self._read_bytes or DEFAULT_TRANSFER_BYTES,
            queue_transfers=self._queue_transfers,
            describe=f"DAVIS {self.info.serial}",
        )

    @property
    def reader_kind(self) -> str:
        """``"ring"`` (asynchronous transfers in flight), ``"sync"`` (a read thread) or ``""`` before the first
        start."""
        return {RingReader: "ring", TransferReader: "sync"}.get(type(self._reader), "")

    def stop(self) -> None:
        """Stop streaming: ``davisDataStop`` (§7.2), then stop the reader thread.

        Data already read stays available to :meth:`read` / :meth:`chunks`. Safe to call when not running or
        after the camera vanished (the wire sequence is then skipped).
        """
        if not self._running:
            if self._reader is not None:
                self._reader.stop()
            return
        self._running = False
        try:
            if not self.transport.disconnected:
                self._steps(stop_sequence())
        except DeviceDisconnectedError:
            pass  # unplugged while stopping: nothing left to switch off
        finally:
            if self._reader is not None:
                self._reader.stop()

    @property
    def debug_messages(self) -> list[DebugMessage]:
        """Messages from the FX3 debug endpoint (firmware error reports) since open, in or outside a run, oldest
        first."""
        return self._debug_reader.messages if self._debug_reader is not None else []

    def add_raw_listener(self, listener: Callable[[bytes], Any]) -> None:
        """Register ``listener(transfer_bytes)``, called with every raw USB transfer (in order, before decoding,
        in the thread that consumes :meth:`chunks`)."""
        self._listeners.append(listener)

    def remove_raw_listener(self, listener: Callable[[bytes], Any]) -> None:
        """Unregister a raw listener (no error if absent)."""
        if listener in self._listeners:
            self._listeners.remove(listener)

    def read(self, timeout_s: float | None = None) -> DecodedChunk | None:
        """Decode the next USB transfer, together with any transfers already queued behind it.

        Raw listeners see every transfer separately and in order; decoding joins consecutive even-length
        transfers (up to ``batch_bytes``) into one decoder call, which gives the same result because the decoder
        carries its state across transfers (an odd-length transfer is decoded on its own so its trailing byte is
        dropped exactly as libcaer does).

        Args:
            timeout_s: how long to wait for a transfer, s (``None`` = until one arrives or acquisition ends).

        Returns:
            The decoded chunk, or ``None`` if nothing arrived within ``timeout_s`` or acquisition has ended and
            every transfer read has been delivered.

        Raises:
            DeviceError: never started.
            DeviceDisconnectedError: the camera vanished; raised after every transfer read before has been
                returned.
        """
        if self._reader is None or self._decoder is None:
            raise DeviceError(f"DAVIS {self.info.serial}: not started")
        with self._consumer_lock:
            try:
                data = self._reader.get(timeout_s)
            except DeviceDisconnectedError:
                self._running = False
                raise
            if data is None:
                return None
            transfers = [data]
            total = len(data)
            while total < self._batch_bytes and (more := self._reader.get_nowait()) is not None:
                transfers.append(more)
                total += len(more)
            for transfer in transfers:
                for listener in list(self._listeners):
                    listener(transfer)
            self._decoded_transfers += len(transfers)
            return self._decode(transfers)

    def _decode(self, transfers: list[bytes]) -> DecodedChunk:
        assert self._decoder is not None
        if len(transfers) == 1:
            return self._decoder.feed(transfers[0])
        chunks: list[DecodedChunk] = []
        run: list[bytes] = []
        for transfer in transfers:
            if len(transfer) % 2:
                if run:
                    chunks.append(self._decoder.feed(b"".join(run)))
                    run = []
                chunks.append(self._decoder.feed(transfer))
            else:
                run.append(transfer)
        if run:
            chunks.append(self._decoder.feed(b"".join(run)))
        return chunks[0] if len(chunks) == 1 else DecodedChunk.concatenate(chunks)

    def chunks(self, timeout_s: float | None = None) -> Iterator[DecodedChunk]:
        """Iterate over decoded transfers until acquisition ends (or ``timeout_s`` passes without data).

        Args:
            timeout_s: end the iteration after this many seconds without data; ``None`` = only when
                :meth:`stop` is called (from another thread) and all data read has been delivered.

        Yields:
            One :class:`~davis_rig.protocol.decoder.DecodedChunk` per :meth:`read` (one or more USB transfers;
            may be empty).

        Raises:
            DeviceDisconnectedError: the camera vanished (after the data read before it was yielded).
        """
        while True:
            chunk = self.read(timeout_s)
            if chunk is None:
                return
            yield chunk

    @property
    def stats(self) -> CameraStats:
        """Counters since the last start (zeros before the first)."""
        reader = self._reader.stats if self._reader is not None else None
        decoder = self._decoder.stats if self._decoder is not None else DecoderStats()
        return CameraStats(
            transfers=reader.transfers if reader else 0,
            bytes=reader.bytes if reader else 0,
            dropped_transfers=reader.dropped_transfers if reader else 0,
            dropped_bytes=reader.dropped_bytes if reader else 0,
            timeouts=reader.timeouts if reader else 0,
            stalls=self.transport.stalls + (reader.stalls if reader else 0),
            decoded_transfers=self._decoded_transfers,
            decoder=decoder,
        )
