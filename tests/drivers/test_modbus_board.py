"""The drive-board driver against a real pymodbus server: loopback TCP and RTU over a pty pair."""

from __future__ import annotations

import pytest
from boardsim import BoardServer, PtyBridge

from usmswitch.drivers import EventKind, FaultCode, VirtualClock
from usmswitch.drivers.daq import DaqError
from usmswitch.drivers.modbus_board import (
    BoardError,
    BoardStatus,
    ModbusBoard,
    Reg,
    RegisterMap,
    parse_modbus_spec,
)


@pytest.fixture
def tcp_server():
    srv = BoardServer("tcp").start()
    yield srv
    srv.stop()


def test_tcp_configure_and_read(tcp_server: BoardServer) -> None:
    clock = VirtualClock(123)
    with ModbusBoard(f"tcp:127.0.0.1:{tcp_server.port}?timeout_ms=300", clock=clock) as board:
        board.configure(40_500, 480)
        st = tcp_server.state
        assert (st.frequency_hz, st.voltage_vpp, st.enabled) == (40_500, 480, 1)
        st.temperature_c = 27.35
        rd = board.read()
        assert rd.frequency_hz == 40_500 and rd.voltage_vpp == 480
        assert rd.temperature_c == pytest.approx(27.35)
        assert BoardStatus.ENABLED in rd.status
        st.temperature_c = -3.5  # a signed register
        cond = board.conditions()
        assert cond is not None and cond.temperature_c == pytest.approx(-3.5)
        board.set_enabled(False)
        assert st.enabled == 0 and board.read().frequency_hz == 0
        assert board.ok and board.failures == 0 and board.take_events() == []


def test_bad_values_are_refused_before_the_wire(tcp_server: BoardServer) -> None:
    with ModbusBoard(f"tcp:127.0.0.1:{tcp_server.port}") as board:
        writes = tcp_server.state.writes
        with pytest.raises(ValueError, match="frequency_hz"):
            board.set_frequency(90_000)
        with pytest.raises(ValueError, match="voltage_vpp"):
            board.set_voltage(0)
        with pytest.raises(ValueError, match="enable"):
            board.set_enabled(1)  # type: ignore[arg-type]
        assert tcp_server.state.writes == writes


def test_board_that_stops_answering_is_a_fault_not_a_crash(tcp_server: BoardServer) -> None:
    clock = VirtualClock(5_000)
    with ModbusBoard(f"tcp:127.0.0.1:{tcp_server.port}?timeout_ms=100", clock=clock) as board:
        assert board.read().temperature_c == pytest.approx(25.0)
        tcp_server.state.hang = True
        with pytest.raises(BoardError, match="modbus tcp"):
            board.read()
        assert isinstance(BoardError("x"), DaqError)
        assert board.conditions() is None  # logged and swallowed on the records path
        assert not board.ok and board.failures == 2
        events = board.take_events()
        assert len(events) == 1  # one FAULT per transition, not per failed poll
        ev = events[0]
        assert ev.kind is EventKind.FAULT and ev.fault is FaultCode.DRIVE and ev.t_ns == 5_000
        tcp_server.state.hang = False
        # The hung replies may still be in flight: the driver recovers on a later poll.
        for _ in range(30):
            if board.conditions() is not None:
                break
        assert board.ok


def test_board_gone_then_back(tcp_server: BoardServer) -> None:
    port = tcp_server.port
    board = ModbusBoard(f"tcp:127.0.0.1:{port}?timeout_ms=100")
    board.open()
    board.set_frequency(40_000)
    tcp_server.stop()
    with pytest.raises(BoardError):
        board.set_frequency(40_100)
    assert not board.ping()
    srv = BoardServer("tcp", port=port).start()
    try:
        for _ in range(50):
            if board.ping():
                break
        board.set_frequency(40_100)
        assert srv.state.frequency_hz == 40_100 and board.ok
    finally:
        board.close()
        srv.stop()


def test_cannot_connect_is_a_board_error() -> None:
    from boardsim import free_port

    board = ModbusBoard(f"tcp:127.0.0.1:{free_port()}?timeout_ms=50")
    with pytest.raises(BoardError, match="cannot connect"):
        board.open()
    assert len(board.take_events()) == 1


def test_rtu_over_a_pty_pair() -> None:
    bridge = PtyBridge()
    srv = BoardServer("rtu", path=bridge.b, unit=3).start()
    try:
        # parity=N: a pty refuses even parity (the default), which a USB-serial adapter takes.
        with ModbusBoard(f"rtu:{bridge.a}:19200?unit=3&timeout_ms=500&parity=N") as board:
            board.configure(41_000, 450)
            assert (srv.state.frequency_hz, srv.state.voltage_vpp, srv.state.enabled) == (41_000, 450, 1)
            srv.state.temperature_c = 31.25
            rd = board.read()
            assert rd.temperature_c == pytest.approx(31.25) and rd.frequency_hz == 41_000
    finally:
        srv.stop()
        bridge.close()


def test_rtu_parity_is_passed_to_the_serial_line() -> None:
    # A pty cannot carry parity (Linux refuses PARENB on one), so the line itself is checked only
    # for N (test_rtu_over_a_pty_pair); E and O are checked where they leave us: pymodbus's serial
    # client parameters, which it hands to pyserial.
    assert parse_modbus_spec("rtu:/dev/ttyUSB1:19200").parity == "E"  # the Modbus serial default
    for parity in ("E", "O", "N"):
        board = ModbusBoard(f"rtu:/dev/ttyUSB1:19200?parity={parity}")
        assert board.spec.parity == parity
        assert board._client.comm_params.parity == parity
        assert (board._client.comm_params.bytesize, board._client.comm_params.stopbits) == (8, 1)


def test_register_map_is_configurable(tcp_server: BoardServer) -> None:
    # Read the setpoints back as if the board mirrored them in holding registers.
    rmap = RegisterMap.from_dict(
        {"frequency": {"table": "holding", "address": 0}, "voltage": {"table": "holding", "address": 1}}
    )
    assert rmap.frequency == Reg("holding", 0)
    with ModbusBoard(f"tcp:127.0.0.1:{tcp_server.port}", registers=rmap) as board:
        board.set_frequency(39_600)
        assert board.read().frequency_hz == 39_600  # enabled=0, yet holding 0 is the setpoint


@pytest.mark.parametrize(
    ("config", "match"),
    [
        ({"temprature": {"address": 3}}, "unknown register 'temprature'"),
        ({"temperature": {"adress": 3}}, "unknown key"),
        ({"temperature": {"address": 70000}}, "address"),
        ({"enable": {"table": "input"}}, "holding"),
        ({"status": {"scale": 0}}, "scale"),
    ],
)
def test_register_map_errors_name_the_key(config: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        RegisterMap.from_dict(config)


def test_spec_parsing() -> None:
    s = parse_modbus_spec("tcp:127.0.0.1:5020")
    assert (s.kind, s.target, s.port_or_baud, s.unit) == ("tcp", "127.0.0.1", 5020, 1)
    s = parse_modbus_spec("rtu:/dev/ttyUSB1:19200?unit=7&parity=E&timeout_ms=150")
    assert (s.kind, s.target, s.port_or_baud, s.unit, s.parity, s.timeout_ms) == (
        "rtu",
        "/dev/ttyUSB1",
        19200,
        7,
        "E",
        150,
    )
    assert parse_modbus_spec("tcp:[::1]:502").target == "::1"
    for bad, match in [
        ("udp:1.2.3.4:502", "tcp: or rtu:"),
        ("tcp:1.2.3.4", "HOST:PORT"),
        ("tcp:1.2.3.4:70000", "not in 1..65535"),
        ("rtu:/dev/ttyUSB0:12345", "baud 12345"),
        ("tcp:h:502?unit=300", "unit"),
        ("tcp:h:502?colour=red", "colour"),
    ]:
        with pytest.raises(ValueError, match=match):
            parse_modbus_spec(bad)


def test_a_late_reply_is_never_taken_for_a_write(tcp_server: BoardServer) -> None:
    """A read answered after its timeout: the write that follows is done only once the board holds it."""
    with ModbusBoard(f"tcp:127.0.0.1:{tcp_server.port}?timeout_ms=100") as board:
        board.set_frequency(40_000)
        for attempt in range(3):
            tcp_server.state.delay_next_s = 0.15  # the read's reply comes after the client gave up
            with pytest.raises(BoardError):
                board.read()
            want = 40_100 + 100 * attempt
            board.set_frequency(want)
            assert tcp_server.state.frequency_hz == want  # held when set_frequency returned
        assert board.ok


def test_a_write_the_board_does_not_hold_is_an_error(tcp_server: BoardServer) -> None:
    tcp_server.state.clamp_frequency_hz = 41_000
    with ModbusBoard(f"tcp:127.0.0.1:{tcp_server.port}?timeout_ms=200") as board:
        board.set_frequency(40_500)
        with pytest.raises(BoardError, match="the board holds 41000, not 41500"):
            board.set_frequency(41_500)
