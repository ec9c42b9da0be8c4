"""Wire-level tests of the drivers against recorded conversations (exact bytes both ways).

The APT requests are compared with the independent encoder of the ``thorlabs-apt-protocol``
package and the scripted replies are checked with its decoder, so neither side of the
conversation is written by fluxmap's own APT code.
"""

import struct
import time

import pytest
import thorlabs_apt_protocol as tap

from fluxcli.hardware import DeviceError
from fluxcli.hardware.apt_labjack import AptLabJack
from fluxcli.hardware.fw102c import FW102C
from scripted_port import ScriptedPort

# ----------------------------------------------------------------------------- FW102C
CONNECT = [
    (b"\r", b"\x00\rCommand error CMD_NOT_DEFINED\n> "),   # the stray NUL and the bare-CR error at connect
    (b"pcount?\r", b"pcount?\r6\r> "),
]


def test_fw102c_connect_noise_and_every_command():
    port = ScriptedPort(CONNECT + [
        (b"*idn?\r", b"*idn?\rTHORLABS FW102C/FW212C Filter Wheel version 1.04\r> "),
        (b"pos?\r", b"pos?\r1\r> "),
        # move_to: where are we, go, read back
        (b"pos?\r", b"pos?\r1\r> "),
        (b"pos=4\r", b"pos=4\r> "),
        (b"pos?\r", b"pos?\r4\r> "),
        (b"sensors=0\r", b"sensors=0\r> "),
        (b"sensors?\r", b"sensors?\r0\r> "),
        (b"speed=1\r", b"speed=1\r> "),
    ])
    wheel = FW102C(port, filters={"650nm": 4})
    assert wheel.identify() == "THORLABS FW102C/FW212C Filter Wheel version 1.04"
    assert wheel.position == 1
    assert wheel.select("650nm") == 4
    wheel.set_sensors(False)
    wheel.set_speed(True)
    port.assert_done()


def test_fw102c_empty_lines_and_newlines_do_not_break_a_position_read():
    port = ScriptedPort(CONNECT + [(b"pos?\r", b"pos?\r\n\r\n5\r\n> ")])
    assert FW102C(port).position == 5
    port.assert_done()


def test_fw102c_error_reply_is_a_device_error_naming_what_it_said():
    port = ScriptedPort(CONNECT + [
        (b"pos?\r", b"pos?\r2\r> "),
        (b"pos=3\r", b"pos=3\rCommand error CMD_ARG_INVALID\n> "),
    ])
    wheel = FW102C(port)
    with pytest.raises(DeviceError) as err:
        wheel.move_to(3)
    msg = str(err.value)
    assert "filter wheel" in msg and "scripted://wire" in msg and "CMD_ARG_INVALID" in msg
    port.assert_done()


def test_fw102c_garbled_reply_is_retried():
    port = ScriptedPort(CONNECT + [
        (b"pos?\r", b"\x8f\xa4\r\xb3> "),          # line noise ending in something like a prompt
        (b"pos?\r", b"pos?\r2\r> "),
    ])
    assert FW102C(port).position == 2
    port.assert_done()


def test_fw102c_wrong_position_after_a_move_is_retried_then_refused():
    moves = [(b"pos?\r", b"pos?\r1\r> "), (b"pos=2\r", b"pos=2\r> "), (b"pos?\r", b"pos?\r3\r> ")]
    port = ScriptedPort(CONNECT + moves + moves)
    wheel = FW102C(port)
    with pytest.raises(DeviceError, match="asked for position 2, the wheel reports 3"):
        wheel.move_to(2)
    port.assert_done()


def test_fw102c_pcount_mismatch_and_silence_are_clear_errors():
    port = ScriptedPort([CONNECT[0], (b"pcount?\r", b"pcount?\r12\r> ")])
    with pytest.raises(DeviceError, match="12 positions"):
        FW102C(port, positions=6)
    silent = ScriptedPort([(b"\r", b"")])
    with pytest.raises(DeviceError, match="no prompt within 0.05 s at connect"):
        FW102C(silent, timeout_s=0.05)


# ----------------------------------------------------------------------------- APT lab jack
HOST, UNIT = 0x01, 0x50
CPM = 134737.0


def reply(msgid: int, payload: bytes) -> bytes:
    """A data message from the controller to the host, written out here from the APT manual."""
    return struct.pack("<HHBB", msgid, len(payload), HOST | 0x80, UNIT) + payload


def decoded(raw: bytes):
    """Every message of ``raw`` as the thorlabs-apt-protocol decoder reads it."""
    import io

    return list(tap.Unpacker(io.BytesIO(raw), on_error="raise"))


INFO = reply(0x0006, struct.pack("<l8sH4B60sHHH", 49000123, b"L490MZ\0\0", 16, 3, 0, 1, 0,
                                 b"lab jack".ljust(60, b"\0"), 1, 0, 1))
VEL_DEFAULT = reply(0x0415, struct.pack("<Hlll", 1, 0, 1482, 7232682))
WANT_VEL = (0, round(0.5 * CPM / 90.9), round(0.5 * CPM * 53.68))
VEL_SET = reply(0x0415, struct.pack("<Hlll", 1, *WANT_VEL))


def status(bits: int) -> bytes:
    return reply(0x042A, struct.pack("<HI", 1, bits))


def poscounter(counts: int) -> bytes:
    return reply(0x0412, struct.pack("<Hl", 1, counts))


def req_statusbits() -> bytes:
    """MOT_REQ_STATUSBITS: the package has no named encoder for 0x0429, so its generic header packer."""
    return tap.functions._pack(0x0429, UNIT, HOST, param1=1)


IDLE = 0x80000000 | 0x2000 | 0x100
MOVING = 0x80000000 | 0x20 | 0x100

APT_CONNECT = [
    (tap.hw_stop_updatemsgs(UNIT, HOST), b""),
    (tap.hw_req_info(UNIT, HOST), INFO),
    (tap.mod_set_chanenablestate(UNIT, HOST, 1, 1), b""),
    (tap.mot_req_velparams(UNIT, HOST, 1), VEL_DEFAULT),
    (tap.mot_set_velparams(UNIT, HOST, 1, *WANT_VEL), b""),
    (tap.mot_req_velparams(UNIT, HOST, 1), VEL_SET),
    (req_statusbits(), status(IDLE | 0x1)),
]


def test_scripted_apt_replies_decode_with_the_independent_decoder():
    info, = decoded(INFO)
    assert (info.serial_number, info.model_number.rstrip(b"\0"), info.nchs) == (49000123, b"L490MZ", 1)
    assert tuple(info.firmware_version) == (1, 0, 3)   # major.minor.patch, stored patch first
    vel, = decoded(VEL_SET)
    assert (vel.min_velocity, vel.acceleration, vel.max_velocity) == WANT_VEL
    st, = decoded(status(MOVING))
    assert st.moving_reverse and st.motor_connected and not st.settled  # (its name for 0x20)


def test_apt_connect_reads_info_enables_sets_velocity_and_never_homes():
    port = ScriptedPort(APT_CONNECT + [(tap.mod_identify(UNIT, HOST, 1), b""), (tap.hw_req_info(UNIT, HOST), INFO)])
    jack = AptLabJack(port, counts_per_mm=CPM)
    assert jack.default_velparams == (0, 1482, 7232682)
    assert jack.identify() == "L490MZ s/n 49000123, firmware 1.0.3"
    port.assert_done()
    assert not any(w[:2] == struct.pack("<H", 0x0443) for w in port.written)  # no MOT_MOVE_HOME


def test_apt_move_skips_unsolicited_messages_and_reads_back():
    target = round(12.5 * CPM)
    unsolicited = (reply(0x0481, struct.pack("<HllI", 1, 10, 10, MOVING))
                   + reply(0x0491, struct.pack("<HlHHI", 1, 10, 0, 0, MOVING))
                   + reply(0x0464, struct.pack("<HllI", 1, target, target, IDLE))
                   + reply(0x0466, struct.pack("<HllI", 1, target, target, IDLE))
                   + struct.pack("<HBBBB", 0x0444, 1, 0, HOST, UNIT))
    assert [m.msg for m in decoded(unsolicited)] == ["mot_get_statusupdate", "mot_get_dcstatusupdate",
                                                     "mot_move_completed", "mot_move_stopped", "mot_move_homed"]
    port = ScriptedPort(APT_CONNECT + [
        (tap.mot_req_poscounter(UNIT, HOST, 1), poscounter(0)),
        (tap.mot_move_absolute(UNIT, HOST, 1, target), b""),
        (req_statusbits(), status(MOVING)),
        (req_statusbits(), unsolicited + status(IDLE)),   # replies arrive mid-wait
        (tap.mot_req_poscounter(UNIT, HOST, 1), reply(0x0481, struct.pack("<HllI", 1, target, target, IDLE))
         + poscounter(target)),
    ])
    jack = AptLabJack(port, counts_per_mm=CPM, time_scale=0.001)
    assert jack.move_to_mm(12.5) == target / CPM
    port.assert_done()


def test_apt_home_and_stop_only_when_asked():
    home_params = reply(0x0442, struct.pack("<HHHll", 1, 2, 1, round(0.4 * CPM * 53.68), 0))
    hp, = decoded(home_params)
    assert (hp.home_dir, hp.home_velocity) == (2, round(0.4 * CPM * 53.68))
    port = ScriptedPort(APT_CONNECT + [
        (tap.mot_req_homeparams(UNIT, HOST, 1), home_params),
        (tap.mot_move_home(UNIT, HOST, 1), b""),
        (req_statusbits(), status(MOVING | 0x200)),
        (req_statusbits(), struct.pack("<HBBBB", 0x0444, 1, 0, HOST, UNIT) + status(IDLE | 0x400)),
        (tap.mot_req_poscounter(UNIT, HOST, 1), poscounter(0)),
        (tap.mot_move_stop(UNIT, HOST, 1, 1), b""),
        (req_statusbits(), status(IDLE | 0x400)),
        (tap.mot_req_poscounter(UNIT, HOST, 1), poscounter(0)),
    ])
    jack = AptLabJack(port, counts_per_mm=CPM, time_scale=0.001)
    assert jack.home() == 0.0
    jack.stop(immediate=True)
    port.assert_done()


def test_apt_travel_limits_are_enforced_before_anything_is_sent():
    port = ScriptedPort(APT_CONNECT)
    jack = AptLabJack(port, counts_per_mm=CPM, travel_mm=(0.0, 50.0))
    for z in (-0.1, 50.001):
        with pytest.raises(DeviceError, match=r"outside the travel \[0, 50\] mm"):
            jack.move_to_mm(z)
    port.assert_done()   # nothing more was written


def test_apt_rich_error_reply_is_a_device_error_with_its_notes():
    rich = reply(0x0081, struct.pack("<HH64s", 0x0411, 11, b"position counter unavailable"))
    assert decoded(rich)[0].code == 11
    port = ScriptedPort(APT_CONNECT + [(tap.mot_req_poscounter(UNIT, HOST, 1), rich)])
    jack = AptLabJack(port, counts_per_mm=CPM)
    with pytest.raises(DeviceError) as err:
        jack.position_mm()
    msg = str(err.value)
    assert "stage (APT lab jack)" in msg and "scripted://wire" in msg and "position counter unavailable" in msg


def test_apt_noise_before_a_reply_resynchronises_and_retries():
    port = ScriptedPort(APT_CONNECT + [
        (tap.mot_req_poscounter(UNIT, HOST, 1), bytes(range(0x90, 0x9A)) + poscounter(7)),
        (tap.mot_req_poscounter(UNIT, HOST, 1), poscounter(7)),
    ])
    jack = AptLabJack(port, counts_per_mm=CPM)
    assert jack.position_mm() == pytest.approx(7 / CPM)
    port.assert_done()


def test_apt_velocity_not_taken_is_refused():
    script = APT_CONNECT[:5] + [(tap.mot_req_velparams(UNIT, HOST, 1), VEL_DEFAULT)]
    with pytest.raises(DeviceError, match="velocity parameters"):
        AptLabJack(ScriptedPort(script), counts_per_mm=CPM)


class _Babbler(ScriptedPort):
    """After the recorded conversation, the device only babbles: ``chatter`` on every read, for ever."""

    def __init__(self, conversation, chatter: bytes):
        super().__init__(conversation)
        self.chatter = chatter

    def read(self, size: int = 1) -> bytes:
        out = super().read(size)
        if out or self.conversation:
            return out
        time.sleep(0.001)
        return self.chatter

    @property
    def in_waiting(self) -> int:
        return max(1, len(self._rx))


def test_a_device_that_only_babbles_is_still_bounded():
    """A stream of status updates (APT) or of noise (FW102C) must not keep a wait alive."""
    update = reply(0x0481, struct.pack("<HllI", 1, 0, 0, IDLE))
    port = _Babbler(APT_CONNECT + [(tap.mot_req_poscounter(UNIT, HOST, 1), b"")], update)
    jack = AptLabJack(port, counts_per_mm=CPM, timeout_s=0.2, retries=0)
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="no reply to MOT_REQ_POSCOUNTER within 0.2 s"):
        jack.position_mm()
    assert time.monotonic() - t0 < 1.0
    wheel_port = _Babbler(CONNECT + [(b"pos?\r", b"")], b"\x93")
    wheel = FW102C(wheel_port, timeout_s=0.2, retries=0)
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="no prompt within 0.2 s after 'pos\\?'"):
        wheel.position
    assert time.monotonic() - t0 < 1.0
