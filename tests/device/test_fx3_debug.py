"""FX3 debug-endpoint message parsing (PROTOCOL.md §2)."""

from davis_rig.device.debug import parse_debug_message


def test_error_report_fields():
    msg = parse_debug_message(bytes([0, 3]) + bytes.fromhex("78563412") + b"USB stall")
    assert (msg.is_error, msg.error_code, msg.time_value, msg.text) == (True, 3, 0x12345678, "USB stall")


def test_short_or_non_zero_first_byte_is_unknown():
    assert not parse_debug_message(bytes([0, 1, 2, 3, 4, 5])).is_error  # 6 bytes: too short
    unknown = parse_debug_message(b"\x01abcdefgh")
    assert not unknown.is_error and unknown.raw == b"\x01abcdefgh" and unknown.error_code is None


def test_non_ascii_text_is_replaced_not_raised():
    msg = parse_debug_message(bytes([0, 9, 0, 0, 0, 0]) + b"\xffok")
    assert msg.is_error and msg.text == "\ufffdok"
