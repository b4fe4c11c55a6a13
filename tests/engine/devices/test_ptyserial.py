"""The pty edge: stable path across unplug/replug, DTR through the pty:// URL handler."""

from __future__ import annotations

import os

import pytest
import serial

from isac_twin.devices.ptyserial import PtyPort, register_modem_listener, unregister_modem_listener


def test_unplug_replug_keeps_the_path(tmp_path):
    port = PtyPort(str(tmp_path / "ttyUSB0"))
    first = port.plug()
    client = serial.serial_for_url(port.link_path, timeout=0.2)
    client.write(b"hi")
    assert os.read(port.master_fd, 10) == b"hi"
    assert port.write(b"yo") == 2 and client.read(2) == b"yo"
    port.unplug()
    assert not os.path.exists(port.link_path)
    with pytest.raises(serial.SerialException):
        client.read(1)  # EIO, as when the USB device vanishes
    client.close()
    with pytest.raises(serial.SerialException):
        serial.serial_for_url(port.link_path)
    port.plug()
    assert os.path.realpath(port.link_path) == port.slave_name and os.path.exists(port.link_path)
    client = serial.serial_for_url(port.link_path, timeout=0.2)
    client.write(b"again")
    assert os.read(port.master_fd, 10) == b"again"
    client.close()
    port.unplug()
    assert first  # a /dev/pts/N


def test_pty_url_records_dtr_and_notifies(tmp_path):
    port = PtyPort(str(tmp_path / "ttyUSB0"))
    port.plug()
    seen = []
    with pytest.raises(OSError):  # a bare pty nobody emulates has no modem lines
        bare = serial.serial_for_url(port.link_path)
        try:
            bare.dtr = False
        finally:
            bare.close()
    register_modem_listener(port.link_path, lambda line, state: seen.append((line, state)))
    try:
        bare = serial.serial_for_url(port.link_path)  # served: plain pyserial keeps them too
        bare.dtr = False
        bare.close()
        assert seen[-1] == ("DTR", False)
        ser = serial.serial_for_url("pty://" + port.link_path)
        ser.dtr = False
        ser.rts = False
        assert [(line, st) for _, line, st in ser.modem_log][-2:] == [("DTR", False), ("RTS", False)]
        assert ("DTR", True) in seen and seen[-2:] == [("DTR", False), ("RTS", False)]  # open asserts DTR
        ser.close()
    finally:
        unregister_modem_listener(port.link_path)
        port.unplug()
