"""The socketcand codec (sans-IO parser and formatter), with property tests against
python-can's own encoder and decoder. The server is tested in tests/emulators/test_socketcand.py."""

from __future__ import annotations

from fractions import Fraction

import can
import pytest
from can.interfaces.socketcand.socketcand import (
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from protocols.socketcand import (
    CanFrame,
    Command,
    MessageReader,
    SocketcandProtocolError,
    encode_frame,
    format_frame,
    format_send,
    format_timestamp,
    parse_command,
)


def test_parse_examples() -> None:
    assert parse_command(b"< open can0 >") == Command("open", ("can0",), channel="can0")
    assert parse_command(b"<rawmode>") == Command("rawmode")
    assert parse_command(b"< send 1AAAAAAA 2 1 f1 >").frame == CanFrame(0x1AAAAAAA, b"\x01\xf1",
                                                                       True)
    assert parse_command(b"< send 123 2 01 0a  >").frame == CanFrame(0x123, b"\x01\x0a")
    assert parse_command(b"< send 0123 0 >").frame == CanFrame(0x123, b"", False)
    c = parse_command(b"< frame 123 23.424242 1A220344 >")
    assert c.frame == CanFrame(0x123, b"\x1a\x22\x03\x44") and c.timestamp_us == 23_424_242
    assert parse_command(b"< frame 123 1.000000  >").frame == CanFrame(0x123, b"")
    assert parse_command(b"< add 1 0 123 8 11 22 33 44 55 66 77 88 >").args[3] == "8"
    for bad in (b"", b"<", b"< >", b"< open >", b"< open a b >", b"< send 123 >",
                b"< send 123 1 1 2 >", b"< send 123 2 1 >",
                b"< send 123 1 100 >", b"< frame 123 1.5 11 >", b"< frame 123 1.000000 1 >",
                b"< frame 123 1.000000 " + b"00" * 9 + b" >", b"< OPEN x >", b"open x",
                b"< echo 1 >", "< open \u00e9 >".encode()):
        with pytest.raises(SocketcandProtocolError):
            parse_command(bad)
    assert format_frame(0x123, b"\x1a\x22\x03\x44", 23.424242) == (
        b"< frame 123 23.424242 1A220344 >")
    assert format_frame(0x5, b"", 1.9999996, extended=True) == b"< frame 00000005 2.000000  >"
    assert parse_command(format_frame(1, b"", 999_999_999_999.0)).timestamp_us == 10**18 - 10**6
    assert format_send(0x1AAAAAAA, b"\x01\xf1") == b"< send 1AAAAAAA 2 1 f1 >"
    for args in ((0x800, b"", 0.0, False), (0x20000000, b"", 0.0, True),
                 (1, b"123456789", 0.0, None), (1, b"", -1.0, None),
                 (1, b"", float("nan"), None), (1, b"", 1e12, None)):
        with pytest.raises(SocketcandProtocolError):
            format_frame(args[0], args[1], args[2], extended=args[3])


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_parse_arbitrary_bytes_returns_or_raises_the_documented_error(data: bytes) -> None:
    for candidate in (data, b"<" + data + b">", b"< send " + data + b" >"):
        try:
            cmd = parse_command(candidate)
        except SocketcandProtocolError:
            continue
        assert isinstance(cmd, Command) and candidate.startswith(b"<")


TOKENS = st.one_of(
    st.sampled_from(["open", "send", "frame", "rawmode", "bcmmode", "echo", "hi", "ok", "error",
                     "subscribe", "vcan0", "0", "8", "9", "C", "123", "7FF", "800", "1FFFFFFF",
                     "20000000", "ff", "1.000000", "1.5", ""]),
    st.text(alphabet="0123456789abcdefABCDEFxz.-", max_size=10))


@settings(max_examples=200, deadline=None)
@given(st.lists(TOKENS, max_size=12), st.sampled_from([" ", "  ", "\t", " \r\n "]))
def test_parse_token_soup_returns_or_raises_the_documented_error(toks: list[str],
                                                                 sep: str) -> None:
    text = "<" + sep + sep.join(toks) + sep + ">"
    try:
        cmd = parse_command(text.encode())
    except SocketcandProtocolError:
        return
    words = [t for t in toks if t]
    assert (cmd.verb, cmd.args) in ((words[0], tuple(words[1:])), (words[0], ()))
    if cmd.verb in ("send", "frame"):
        assert cmd.frame is not None and len(cmd.frame.data) <= 8


@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(max_size=200), max_size=8))
def test_reader_on_arbitrary_chunks_yields_messages_or_raises(chunks: list[bytes]) -> None:
    reader = MessageReader(max_message=64)
    try:
        for chunk in chunks:
            for m in reader.feed(chunk):
                assert m[:1] == b"<" and m[-1:] == b">" and len(m) <= 64
                assert b"<" not in m[1:-1] and b">" not in m[1:-1]
    except SocketcandProtocolError:
        with pytest.raises(SocketcandProtocolError):  # and it stays failed
            list(reader.feed(b"< echo >"))
    assert reader.pending <= 64


FRAMES = st.builds(
    lambda ext, i, data: CanFrame(i & (0x1FFFFFFF if ext else 0x7FF), data, ext),
    st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))


@settings(max_examples=300, deadline=None)
@given(FRAMES, st.floats(0, 999_999_999_999.0, allow_nan=False))
def test_format_parse_round_trip_and_python_can_agrees(frame: CanFrame, t: float) -> None:
    line = format_frame(frame.can_id, frame.data, t, extended=frame.extended)
    cmd = parse_command(line)
    assert cmd.verb == "frame" and cmd.frame == frame
    assert cmd.timestamp_us is not None  # the nearest microsecond
    assert abs(Fraction(cmd.timestamp_us, 10**6) - Fraction(t)) <= Fraction(1, 2 * 10**6)
    # python-can's own client decodes what the server sends ...
    m = convert_ascii_message_to_can_message(line.decode("ascii"))
    assert m is not None
    assert (m.arbitration_id, m.is_extended_id, bytes(m.data)) == (
        frame.can_id, frame.extended, frame.data)
    assert abs(m.timestamp - t) <= 1e-6 + 1e-15 * t
    # ... and the server parses what python-can's client sends, and what format_send writes
    sent = convert_can_message_to_ascii_message(
        can.Message(arbitration_id=frame.can_id, data=frame.data,
                    is_extended_id=frame.extended))
    assert parse_command(sent.encode("ascii")).frame == frame
    assert parse_command(format_send(frame.can_id, frame.data,
                                     extended=frame.extended)).frame == frame


@settings(max_examples=200, deadline=None)
@given(st.lists(FRAMES, min_size=1, max_size=20), st.data())
def test_reader_splits_any_chunking_of_a_valid_stream(frames: list[CanFrame],
                                                      data: st.DataObject) -> None:
    msgs = [format_send(f.can_id, f.data, extended=f.extended) for f in frames]
    stream = b"".join(m + data.draw(st.sampled_from([b"", b" ", b"\r\n"])) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    reader = MessageReader()
    out: list[bytes] = []
    for lo, hi in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        out += reader.feed(stream[lo:hi])
    assert out == msgs and reader.pending == 0
    assert [parse_command(m).frame for m in out] == frames


@settings(max_examples=200, deadline=None)
@given(FRAMES, st.floats(0, 999_999_999_999.0, allow_nan=False))
def test_encode_frame_with_a_formatted_stamp_is_format_frame(frame: CanFrame, t: float) -> None:
    assert encode_frame(frame, format_timestamp(t)) == format_frame(
        frame.can_id, frame.data, t, extended=frame.extended)
