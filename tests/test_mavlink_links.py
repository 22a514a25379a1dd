"""Links over real sockets and a real (pseudo-terminal) serial port; clear errors for bad ones."""

from __future__ import annotations

import os
import socket
import sys
import time

import pytest

from firmware_bridge import commands
from firmware_bridge.decoder import Heartbeat, TelemetryDecoder
from firmware_bridge.links import LinkError, open_link, parse_connection_string


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_until(link, n: int, deadline_s: float = 2.0) -> bytes:
    data = b""
    end = time.monotonic() + deadline_s
    while len(data) < n and time.monotonic() < end:
        data += link.read(4096, timeout_s=0.05)
    return data


def test_udp_round_trip():
    port = free_udp_port()
    beat = commands.heartbeat()
    with open_link(f"udpin:127.0.0.1:{port}") as server, open_link(f"udpout:127.0.0.1:{port}") as client:
        assert server.read(timeout_s=0.0) == b""
        client.write(beat)
        received = read_until(server, len(beat))
        assert received == beat
        readings = TelemetryDecoder().feed(received)
        assert isinstance(readings[0], Heartbeat) and readings[0].component == 191
        # udpin answers the last sender
        reply = commands.command_long_arm(True)
        server.write(reply)
        assert read_until(client, len(reply)) == reply


def test_tcp_round_trip():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        port = listener.getsockname()[1]
        with open_link(f"tcp:127.0.0.1:{port}") as link:
            peer, _ = listener.accept()
            with peer:
                beat = commands.heartbeat()
                link.write(beat)
                peer.settimeout(2.0)
                assert peer.recv(4096) == beat
                peer.sendall(beat)
                assert read_until(link, len(beat)) == beat


@pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")
def test_serial_over_pseudo_terminal_both_ways():
    master, slave = os.openpty()
    try:
        device = os.ttyname(slave)
        with open_link(device, baud=57600) as link:
            beat = commands.heartbeat()
            link.write(beat)
            got = b""
            end = time.monotonic() + 2.0
            while len(got) < len(beat) and time.monotonic() < end:
                got += os.read(master, 4096)
            assert got == beat
            arm = commands.command_long_arm(True)
            os.write(master, arm)
            received = read_until(link, len(arm))
            assert received == arm
            decoder = TelemetryDecoder()
            decoder.feed(received)
            assert decoder.counters.by_type == {"COMMAND_LONG": 1}
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")
def test_an_unplugged_serial_port_is_a_link_error_naming_it():
    master, slave = os.openpty()
    device = os.ttyname(slave)
    link = open_link(device)
    os.close(slave)
    os.close(master)  # the device goes away under the open port
    try:
        with pytest.raises(LinkError, match=device):
            for _ in range(3):  # the first write may still be buffered; a read or a later write fails
                link.write(commands.heartbeat())
                link.read(64, 0.05)
    finally:
        link.close()


def test_missing_serial_device_names_the_path():
    path = "/dev/ttyDOES_NOT_EXIST_42"
    with pytest.raises(LinkError, match="ttyDOES_NOT_EXIST_42"):
        open_link(path)


@pytest.mark.parametrize(
    "bad",
    ["", "udp:127.0.0.1:14550", "udpin:127.0.0.1", "tcp:127.0.0.1:port", "udpout::14550", "tcp:127.0.0.1:70000"],
)
def test_bad_connection_strings(bad):
    with pytest.raises(LinkError) as info:
        open_link(bad)
    assert repr(bad) in str(info.value)


def test_tcp_refused_is_a_link_error():
    port = free_udp_port()  # very likely nobody listens on TCP there
    with pytest.raises(LinkError, match=f"tcp:127.0.0.1:{port}"):
        open_link(f"tcp:127.0.0.1:{port}")


def test_a_tcp_peer_that_neither_accepts_nor_refuses_fails_within_the_connect_timeout():
    """A listener whose accept queue is full drops new SYNs: connect() would wait for the kernel's retries (minutes)
    without a timeout. The vessel reopens a lost link with a short one so its loop is not held."""
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(0)
    port = listener.getsockname()[1]
    queued = [socket.create_connection(("127.0.0.1", port), timeout=1.0)]  # fills the queue of length 0 (+1)
    try:
        started = time.monotonic()
        with pytest.raises(LinkError, match=f"tcp:127.0.0.1:{port}"):
            for _ in range(3):  # the kernel may still queue one or two more
                queued.append(open_link(f"tcp:127.0.0.1:{port}", connect_timeout_s=0.3).sock)
        assert time.monotonic() - started < 3 * 0.3 + 1.0
    finally:
        for sock in queued:
            sock.close()
        listener.close()


def test_parse_connection_string():
    assert parse_connection_string("udpin:0.0.0.0:14550") == ("udpin", "0.0.0.0", 14550)
    assert parse_connection_string("/dev/ttyACM0") == ("serial", "/dev/ttyACM0", None)
    assert parse_connection_string("COM3") == ("serial", "COM3", None)
