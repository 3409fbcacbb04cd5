"""Davis346 over the virtual backend: §5 read-out, §6/§7 sequences on the wire, data path, faults, clean stop."""

import errno
import threading

import pytest

from davis_rig.device.camera import Davis346
from davis_rig.device.info import DEVICE_INFO_READS
from davis_rig.errors import DeviceDisconnectedError, DeviceError, ProtocolError, TransportError
from davis_rig.protocol.biases import DAVIS346_DEFAULT_BIASES, CoarseFineBias, VdacBias
from davis_rig.protocol.config import Aps, Clocks, ConfigWrite, DeviceFeatures, Module, Mux
from davis_rig.protocol.decoder import DecodedChunk
from davis_rig.protocol.sequences import Sleep, config_writes, default_config_sequence, start_sequence, stop_sequence
from davis_rig.usb.sources import Faults, TransferListSource
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend, usb_error

from tests.helpers.camera_reads import read_until_drained
from tests.helpers.davis346_vectors import VECTOR_IDS, VECTORS, assert_matches_expected, vector_transfers
from tests.helpers.libusb_emu import usb_backend  # noqa: F401  (fixture: every test runs on the virtual and the emulated libusb)

CLOCKS = Clocks(logic_mhz=104, adc_mhz=30, usb_mhz=80, deviation=1000)
FEATURES = DeviceFeatures(dvs_has_background_activity_filter=True, dvs_has_roi_filter=True, aps_has_global_shutter=True)


def open_camera(usb_backend, device, **kwargs):
    sleeps = []
    cam = Davis346.open(backend=usb_backend.plug(device), sleep=sleeps.append, read_timeout_ms=10, **kwargs)
    return cam, sleeps


def test_open_reads_device_info(usb_backend):
    dev = VirtualDavis346(serial="CAM00042", clocks=CLOCKS, features=FEATURES)
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        info = cam.info
        assert (info.serial, info.firmware_version, info.logic_version, info.logic_patch) == ("CAM00042", 6, 18, 1)
        assert info.chip_id == 5 and info.is_davis346 and info.is_master
        assert info.layout.dvs_hw == (260, 346) and info.dvs_size_xy == (346, 260) == info.aps_size_xy
        assert info.clocks == CLOCKS and info.features == FEATURES
        assert info.to_dict()["device_info"]["dvs_size_columns"] == 346
    assert dev.reads == [(6, 0), (6, 7)] + list(DEVICE_INFO_READS)


def test_open_with_inverted_orientation_reports_user_sizes(usb_backend):
    layout = dict(VECTORS[0]["device_info"], dvs_size_columns=260, dvs_size_rows=346, dvs_orientation_info=4)
    cam, _ = open_camera(usb_backend, VirtualDavis346(layout=layout))
    with cam:
        assert cam.info.dvs_size_xy == (346, 260)


def test_send_default_config_writes_exactly_libcaer_defaults(usb_backend):
    dev = VirtualDavis346(clocks=CLOCKS, features=FEATURES)
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        cam.send_default_config()
    expected = config_writes(
        default_config_sequence(
            dvs_size_xy=(346, 260), aps_size_xy=(346, 260), features=FEATURES, clocks=CLOCKS, imu_type=1
        )
    )
    assert dev.writes == expected
    # spot checks straight from PROTOCOL.md §6: first bias, chip config, GS, exposure @ 30 MHz ADC, USB delay @ 80 MHz
    assert dev.writes[0] == ConfigWrite(5, 0, 0x019B)
    assert [w.value for w in dev.writes[:28]] == [e.bias.encode() for e in DAVIS346_DEFAULT_BIASES]
    assert ConfigWrite(5, 142, 1) in dev.writes and ConfigWrite(2, 7, 1) in dev.writes
    assert ConfigWrite(2, 12, 120_000) in dev.writes and ConfigWrite(2, 13, 1_200_000) in dev.writes
    assert dev.writes[-1] == ConfigWrite(9, 1, 80_000)
    assert all(r.request == 0xBF for r in dev.control_log if r.request_type == 0x40)  # one write per request


def test_start_and_stop_sequences_on_the_wire_are_libcaers_imu_included(usb_backend):
    dev = VirtualDavis346()
    cam, sleeps = open_camera(usb_backend, dev)
    with cam:
        assert cam.producers == {"dvs": True, "aps": True, "imu": True, "extinput": True}
        n0 = len(dev.writes)
        cam.start()
        assert cam.running and dev.streaming
        started = dev.writes[n0:]
        cam.stop()
        stopped = dev.writes[n0 + len(started):]
    expected_start = start_sequence()  # libcaer's davisDataStart: the IMU (accelerometer, gyroscope, temperature) too
    assert started == config_writes(expected_start)
    assert {ConfigWrite(3, 2, 1), ConfigWrite(3, 3, 1), ConfigWrite(3, 4, 1)} <= set(started)
    assert sleeps == [s.duration_us / 1e6 for s in expected_start if isinstance(s, Sleep)] == [0.01, 0.2, 0.05]
    assert dev.clear_halts == [0x82]
    assert stopped == config_writes(stop_sequence())
    assert not dev.streaming and not dev.claimed


def test_open_default_config_start_stop_is_register_for_register_libcaers_client_flow(usb_backend):
    """PROTOCOL.md §7.3: open → sendDefaultConfig → dataStart → dataStop, every register write in libcaer's
    order."""
    dev = VirtualDavis346(clocks=CLOCKS, features=FEATURES)
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        cam.send_default_config()
        cam.start()
        cam.stop()
    default_config = default_config_sequence(
        dvs_size_xy=(346, 260), aps_size_xy=(346, 260), features=FEATURES, clocks=CLOCKS, imu_type=1
    )
    assert dev.writes == config_writes(default_config) + config_writes(start_sequence()) + config_writes(
        stop_sequence()
    )
    assert dev.reads == [(6, 0), (6, 7)] + list(DEVICE_INFO_READS)
    assert dev.clear_halts == [0x82]


def test_start_with_imu_disabled_omits_only_the_imu_run_writes(usb_backend):
    dev = VirtualDavis346()
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        cam.set_imu_enabled(False)
        cam.start()
        cam.stop()
    started = config_writes(start_sequence(imu=False))
    assert dev.writes[: len(started)] == started
    assert ConfigWrite(3, 2, 1) not in dev.writes


def test_typed_setters(usb_backend):
    dev = VirtualDavis346(clocks=CLOCKS)
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        cam.set_exposure(8000)
        cam.set_frame_interval(33333)
        cam.set_bias("onbn", CoarseFineBias(6, 255))
        cam.set_bias("ADCREFHIGH", 0x0198)  # raw value → VDAC(24, 6)
        cam.set_global_shutter(False)
        cam.timestamp_reset()
        assert cam.exposure_us == 8000 and cam.frame_interval_us == 33333
        assert cam.biases["ONBN"] == CoarseFineBias(6, 255) and cam.biases["ADCREFHIGH"] == VdacBias(24, 6)
        with pytest.raises(ProtocolError, match="expects CoarseFineBias, got VdacBias"):
            cam.set_bias("ONBN", VdacBias(1, 1))
        with pytest.raises(ProtocolError, match="0..4194303"):
            cam.set_exposure(5_000_000)
    assert dev.writes == [
        ConfigWrite(2, 12, 240_000),
        ConfigWrite(2, 13, 999_990),
        ConfigWrite(5, 11, CoarseFineBias(6, 255).encode()),
        ConfigWrite(5, 2, 0x0198),
        ConfigWrite(5, 142, 0),
        ConfigWrite(2, 7, 0),
        ConfigWrite(0, 2, 1),
        ConfigWrite(0, 2, 0),
    ]
    assert dev.control_log[-1].request == 0xC2  # the reset pulse is one multiple-write request


def test_producer_switches_apply_immediately_while_running(usb_backend):
    dev = VirtualDavis346()
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        cam.set_aps_enabled(False)
        cam.start()
        assert ConfigWrite(2, 4, 1) not in dev.writes
        cam.set_aps_enabled(True)
        cam.set_dvs_enabled(False)
        assert dev.writes[-2:] == [ConfigWrite(2, 4, 1), ConfigWrite(1, 3, 0)]
        with pytest.raises(DeviceError, match="already started"):
            cam.start()


#: Both readers: a ring of 8 asynchronous transfers (the default) and a thread of synchronous reads.
READERS = pytest.mark.parametrize("usb_transfers", [8, 0], ids=["ring", "sync"])


def _decode_all(usb_backend, vector, batch_bytes=1 << 20, transfers=None, usb_transfers=8, **faults):
    """Serve ``transfers`` (default: the vector's own) from a virtual camera with the vector's layout, decode all."""
    transfers = vector_transfers(vector) if transfers is None else transfers
    dev = VirtualDavis346(layout=vector["device_info"], source=TransferListSource(transfers), faults=Faults(**faults))
    cam, _ = open_camera(usb_backend, dev, batch_bytes=batch_bytes, usb_transfers=usb_transfers)
    raw = []
    with cam:
        cam.add_raw_listener(raw.append)
        cam.start()
        chunks = read_until_drained(cam, dev, raw)
        stats = cam.stats
    return DecodedChunk.concatenate(chunks), raw, stats


@READERS
@pytest.mark.parametrize("vector", VECTORS, ids=VECTOR_IDS)
def test_every_vector_decodes_through_the_real_pyusb_path(vector, usb_transfers, usb_backend):
    chunk, raw, stats = _decode_all(usb_backend, vector, usb_transfers=usb_transfers)
    assert_matches_expected(chunk, vector["expected"])
    assert raw == [t for t in vector_transfers(vector) if t]
    assert stats.transfers == len(raw) == stats.decoded_transfers and stats.dropped_transfers == 0


@pytest.mark.parametrize("vector", VECTORS, ids=VECTOR_IDS)
@pytest.mark.parametrize("batch_bytes", [0, 1 << 20], ids=["one-transfer-per-read", "batched"])
def test_every_vector_split_at_every_word_boundary_decodes_the_same(vector, batch_bytes, usb_backend):
    data = b"".join(vector_transfers(vector))
    words = [data[i : i + 2] for i in range(0, len(data), 2)]
    chunk, raw, stats = _decode_all(usb_backend, vector, batch_bytes=batch_bytes, transfers=words)
    assert_matches_expected(chunk, vector["expected"])
    assert raw == words and stats.transfers == len(words) and stats.dropped_transfers == 0
    assert stats.decoder.odd_bytes_dropped == 0


@READERS
def test_faults_that_lose_no_data_give_identical_output(usb_transfers, usb_backend):
    vector = next(v for v in VECTORS if v["id"].startswith("V12"))
    clean, _, _ = _decode_all(usb_backend, vector)
    faulty, _, stats = _decode_all(
        usb_backend, vector, usb_transfers=usb_transfers, stall_every=2, timeout_every=3, short_transfer_bytes=2
    )
    assert faulty.events.tolist() == clean.events.tolist()
    assert [f.pixels.tolist() for f in faulty.frames] == [f.pixels.tolist() for f in clean.frames]
    assert stats.stalls > 0


def test_odd_length_transfers_drop_the_extra_byte(usb_backend):
    vector = next(v for v in VECTORS if v["id"].startswith("V01"))
    chunk, raw, stats = _decode_all(usb_backend, vector, odd_length=1)
    assert chunk.events.tolist() == [tuple(e) for e in vector["expected"]["dvs"]]
    assert raw[0].endswith(b"\xa5") and stats.decoder.odd_bytes_dropped == 1


def test_garbage_does_not_crash_the_pipeline(usb_backend):
    vector = next(v for v in VECTORS if v["id"].startswith("V12"))
    chunk, raw, stats = _decode_all(usb_backend, vector, garbage_rate=0.3, seed=3)
    assert stats.decoder.words == sum(len(r) // 2 for r in raw)


@READERS
def test_unplug_delivers_data_read_before_then_raises(usb_transfers, usb_backend):
    transfers = [bytes.fromhex("64800a101430"), bytes.fromhex("96800a101530"), bytes.fromhex("c8800a101630")]
    dev = VirtualDavis346(faults=Faults(disconnect_after_transfers=2))
    cam, _ = open_camera(usb_backend, dev, usb_transfers=usb_transfers)
    got = []
    with cam:
        cam.start()
        dev.attach_source(TransferListSource(transfers))  # the data (and the unplug) come once start() returned
        with pytest.raises(DeviceDisconnectedError):
            for chunk in cam.chunks(timeout_s=2.0):
                got.append(chunk)
        assert not cam.running
    # close() after the unplug did not raise; both transfers read before it were delivered
    assert DecodedChunk.concatenate(got).events.tolist() == [(100, 20, 10, 1), (150, 21, 10, 1)]


@READERS
def test_stop_ends_chunks_from_another_thread_and_joins_the_reader(usb_transfers, usb_backend):
    dev = VirtualDavis346(source=TransferListSource([bytes.fromhex("64800a101430")]))
    cam, _ = open_camera(usb_backend, dev, usb_transfers=usb_transfers)
    with cam:
        cam.start()
        timer = threading.Timer(0.2, cam.stop)
        timer.start()
        chunks = list(cam.chunks())  # no timeout: ends only because stop() was called
        timer.join()
        assert len(chunks) == 1 and not cam.running
        assert cam.reader_kind == ("ring" if usb_transfers else "sync")
        assert all(t.name not in ("davis-usb-reader", "davis-usb-ring") for t in threading.enumerate())
        assert any(t.name == "davis-usb-debug" for t in threading.enumerate())  # 0x81 is read until close
    assert all(not t.name.startswith("davis-usb-") for t in threading.enumerate())


class _FailingWriteDevice(VirtualDavis346):
    """A camera that stalls the first write of one register value (later writes succeed)."""

    def __init__(self, fail_write: tuple[int, int, int], **kwargs):
        super().__init__(**kwargs)
        self.fail_write = fail_write
        self.failed = False

    def _write(self, module, param, value):
        if not self.failed and (int(module), int(param), int(value)) == self.fail_write:
            self.failed = True
            raise usb_error(errno.EPIPE)
        super()._write(module, param, value)


@READERS
def test_a_start_that_fails_after_run_is_on_sends_the_stop_sequence(usb_transfers, usb_backend):
    # APS RUN comes after RUN_CHIP, USB RUN, MUX RUN and DVS RUN: the FPGA already streams events when it fails.
    dev = _FailingWriteDevice((int(Module.APS), int(Aps.RUN), 1))
    cam, _ = open_camera(usb_backend, dev, usb_transfers=usb_transfers)
    with cam:
        with pytest.raises(TransportError):
            cam.start()
        assert not cam.running
        assert not dev.streaming and dev.register(Module.MUX, Mux.RUN_CHIP) == 0
        assert dev.writes[-len(config_writes(stop_sequence())):] == config_writes(stop_sequence())
    assert all(t.name not in ("davis-usb-reader", "davis-usb-ring") for t in threading.enumerate())


def test_a_start_that_fails_on_an_unplugged_camera_raises_the_start_error(usb_backend):
    dev = VirtualDavis346()
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        dev.unplug()
        with pytest.raises(DeviceDisconnectedError):
            cam.start()
        assert not cam.running


@READERS
def test_slow_consumer_drops_whole_transfers_and_counts_them(usb_transfers, usb_backend):
    transfers = [bytes.fromhex("64800a101430")] * 20
    dev = VirtualDavis346(source=TransferListSource(transfers))
    cam, _ = open_camera(usb_backend, dev, queue_transfers=4, usb_transfers=usb_transfers)
    with cam:
        with pytest.warns(RuntimeWarning, match="dropped"):
            cam.start()
            for _ in range(200):
                if len(dev.source) == 0 and cam.stats.transfers + cam.stats.dropped_transfers == 20:
                    break
                threading.Event().wait(0.01)
        chunks = list(cam.chunks(timeout_s=0.1))
        stats = cam.stats
    assert len(DecodedChunk.concatenate(chunks).events) == stats.transfers == stats.decoded_transfers == 4
    assert stats.dropped_transfers == 16
    assert stats.dropped_bytes == 16 * 6


def test_read_before_start_is_an_error(usb_backend):
    cam, _ = open_camera(usb_backend, VirtualDavis346())
    with cam, pytest.raises(DeviceError, match="not started"):
        cam.read(0.01)


class _CountingDevice(VirtualDavis346):
    """A camera whose MUX DVS-dropped counter carries into the upper word between two reads."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.upper_reads = 0

    def register(self, module, param):
        if (module, param) == (0, 83):  # upper word: 0 on the first read, 1 afterwards
            self.upper_reads += 1
            return 0 if self.upper_reads == 1 else 1
        if (module, param) == (0, 84):  # lower word: 0xFFFFFFFF before the carry, 2 after it
            return 0xFFFFFFFF if self.upper_reads == 1 else 2
        return super().register(module, param)


def test_fpga_statistics_read_64_bit_counters_with_carry_detection(usb_backend):
    features = DeviceFeatures(mux_has_statistics=True, dvs_has_statistics=True)
    dev = _CountingDevice(features=features)
    dev.registers.update({(1, 85): 1, (1, 86): 7, (0, 81): 0, (0, 82): 3})
    cam, _ = open_camera(usb_backend, dev)
    with cam:
        n0 = len(dev.reads)
        stats = cam.fpga_statistics()
    assert stats == {
        "mux_extinput_dropped": 3,
        "mux_dvs_dropped": (1 << 32) | 2,  # carry seen: upper re-read differs, lower read again
        "dvs_events_row": 0,
        "dvs_events_column": 0,
        "dvs_events_dropped": (1 << 32) | 7,
    }
    assert dev.reads[n0 + 3 : n0 + 7] == [(0, 83), (0, 84), (0, 83), (0, 84)]
    cam2, _ = open_camera(usb_backend, VirtualDavis346())
    with cam2:
        assert cam2.fpga_statistics() == {}


@READERS
def test_fx3_debug_endpoint_messages_are_collected_from_open_to_close(caplog, usb_transfers, usb_backend):
    dev = VirtualDavis346()
    cam, _ = open_camera(usb_backend, dev, usb_transfers=usb_transfers)

    def wait_for_messages(n):
        for _ in range(300):
            if len(cam.debug_messages) == n:
                return
            threading.Event().wait(0.01)

    with cam, caplog.at_level("WARNING", logger="davis_rig.device"):
        dev.push_debug_message(b"\x07\x01")  # outside a run: libcaer reads 0x81 from open to close
        wait_for_messages(1)
        cam.start()
        dev.push_debug_message(bytes([0x00, 0x2A]) + (1234).to_bytes(4, "little") + b"FIFO overflow\x00junk")
        wait_for_messages(2)
        cam.stop()
        dev.push_debug_message(bytes([0x00, 0x07]) + (99).to_bytes(4, "little") + b"after stop")
        wait_for_messages(3)
        messages = cam.debug_messages
    assert [(m.is_error, m.error_code, m.time_value, m.text) for m in messages] == [
        (False, None, None, ""),
        (True, 42, 1234, "FIFO overflow"),
        (True, 7, 99, "after stop"),
    ]
    assert "firmware error 42 at 1234: FIFO overflow" in caplog.text
    assert all(t.name != "davis-usb-debug" for t in threading.enumerate())


def test_default_config_refuses_non_davis346_chips(usb_backend):
    layout = dict(VECTORS[0]["device_info"], chip_id=2)  # DAVIS240C
    dev = VirtualDavis346(layout=layout)
    cam, _ = open_camera(usb_backend, dev)
    with cam, pytest.raises(DeviceError, match="chip id 2 is not a DAVIS346"):
        cam.send_default_config()
    assert dev.writes == []


@pytest.mark.parametrize("vector", VECTORS, ids=VECTOR_IDS)
def test_batched_decoding_equals_one_transfer_per_read(vector, usb_backend):
    # odd-length transfers inside a batch are decoded alone, so their extra byte is dropped exactly as libcaer does
    one, raw_one, _ = _decode_all(usb_backend, vector, batch_bytes=0, odd_length=2, short_transfer_bytes=4)
    many, raw_many, stats = _decode_all(usb_backend, vector, odd_length=2, short_transfer_bytes=4)
    assert raw_one == raw_many
    assert many.events.tolist() == one.events.tolist() == [tuple(e) for e in vector["expected"]["dvs"]]
    assert [f.pixels.tolist() for f in many.frames] == [f.pixels.tolist() for f in one.frames]
    assert many.specials.tolist() == one.specials.tolist()


class _SyncOnlyBackend(VirtualDavis346Backend):
    """A pyusb backend without libusb's asynchronous transfer API."""

    async_transfers = None


def test_backend_without_async_transfers_falls_back_to_synchronous_reads():
    dev = VirtualDavis346(source=TransferListSource([bytes.fromhex("64800a101430")]))
    cam = Davis346.open(backend=_SyncOnlyBackend(dev), sleep=lambda s: None, read_timeout_ms=10)
    raw = []
    with cam:
        assert cam.transport.async_transfers() is None
        cam.add_raw_listener(raw.append)
        cam.start()
        chunks = read_until_drained(cam, dev, raw)
        assert cam.reader_kind == "sync"
        cam.stop()
    assert DecodedChunk.concatenate(chunks).events.tolist() == [(100, 20, 10, 1)]
