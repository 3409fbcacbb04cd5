"""Real-camera smoke test: runs only with a DAVIS attached (marker ``hardware``), otherwise skipped with the reason."""

import pytest

from davis_rig.errors import MissingDependencyError

pytestmark = pytest.mark.hardware


def _attached():
    from davis_rig.usb.transport import list_devices

    try:
        return list_devices()
    except MissingDependencyError as exc:
        pytest.skip(f"no libusb backend: {exc}")


def test_real_davis346_streams_events():
    devices = _attached()
    if not devices:
        pytest.skip("no DAVIS camera attached (looked for USB 152a:841a / 152a:841b)")
    from davis_rig.device.camera import Davis346

    with Davis346.open(serial=devices[0].serial) as cam:
        assert cam.info.logic_version == 18 and cam.info.is_davis346
        cam.send_default_config()
        cam.start()
        chunks = []
        for chunk in cam.chunks(timeout_s=2.0):
            chunks.append(chunk)
            if sum(len(c.events) for c in chunks) > 1000 or len(chunks) > 500:
                break
        cam.stop()
        stats = cam.stats
    assert stats.transfers > 0 and stats.decoder.words > 0
    assert sum(len(c.events) for c in chunks) > 0, "no DVS events in 2 s: is the lens capped?"
