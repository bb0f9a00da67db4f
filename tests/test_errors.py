"""Error codes and exceptions (docs/protocol.md, "Error codes")."""

from __future__ import annotations

import pytest
from rigs import J1, build_emulated

from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import (
    CommError,
    ConfigError,
    ErrType,
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
    NotInitError,
    StalledError,
    UnknownJointError,
    error_to_string,
)
from bioscara_gym.hardware.registers import Reg

# docs/protocol.md: OK 0, ERROR -1, NOT_HOMED -2, NOT_ENABLED -3, STALLED -4,
# NOT_INIT -5, COMM_ERROR -6, INVALID_ARGUMENT -101, INCORRECT_STATE -109.
SPEC_CODES = {
    "OK": 0,
    "ERROR": -1,
    "NOT_HOMED": -2,
    "NOT_ENABLED": -3,
    "STALLED": -4,
    "NOT_INIT": -5,
    "COMM_ERROR": -6,
    "INVALID_ARGUMENT": -101,
    "INCORRECT_STATE": -109,
}

SUBCLASSES = [
    (NotHomedError, ErrType.NOT_HOMED),
    (NotEnabledError, ErrType.NOT_ENABLED),
    (StalledError, ErrType.STALLED),
    (NotInitError, ErrType.NOT_INIT),
    (CommError, ErrType.COMM_ERROR),
    (InvalidArgumentError, ErrType.INVALID_ARGUMENT),
    (IncorrectStateError, ErrType.INCORRECT_STATE),
]


@pytest.mark.parametrize(("name", "value"), SPEC_CODES.items())
def test_err_type_has_spec_value(name: str, value: int) -> None:
    assert ErrType[name] == value


def test_err_type_has_exactly_the_spec_codes() -> None:
    assert {e.name: e.value for e in ErrType} == SPEC_CODES


@pytest.mark.parametrize("code", list(ErrType))
def test_error_to_string_names_the_code_and_describes_it(code: ErrType) -> None:
    text = error_to_string(code)
    name, _, description = text.partition(": ")
    assert name == code.name
    assert description


@pytest.mark.parametrize("code", list(ErrType))
def test_error_to_string_accepts_plain_int(code: ErrType) -> None:
    assert error_to_string(int(code)) == error_to_string(code)


def test_error_to_string_of_unknown_code() -> None:
    assert error_to_string(42) == "unknown error code 42"


def test_error_descriptions_are_distinct() -> None:
    texts = [error_to_string(code) for code in ErrType]
    assert len(set(texts)) == len(texts)


@pytest.mark.parametrize(("cls", "code"), SUBCLASSES)
def test_joint_error_subclass_carries_its_code(cls: type[JointError], code: ErrType) -> None:
    assert cls.code is code
    assert cls("j1: something").code is code


@pytest.mark.parametrize(("cls", "code"), SUBCLASSES)
def test_joint_error_subclass_is_a_joint_error(cls: type[JointError], code: ErrType) -> None:
    assert issubclass(cls, JointError)


@pytest.mark.parametrize(("cls", "code"), SUBCLASSES)
def test_error_without_message_uses_the_code_description(cls: type[JointError], code: ErrType) -> None:
    assert str(cls()) == error_to_string(code)


def test_generic_error_takes_its_code() -> None:
    err = JointError("boom", joint="j3", code=ErrType.NOT_INIT)
    assert err.code is ErrType.NOT_INIT
    assert str(err) == "j3: boom"


@pytest.mark.parametrize(("cls", "code"), SUBCLASSES)
def test_error_with_joint_prefixes_its_name(cls: type[JointError], code: ErrType) -> None:
    err = cls("something", joint="j2", register=Reg.SETRPM)
    assert str(err) == "j2: something"
    assert (err.joint, err.register) == ("j2", Reg.SETRPM)


def test_error_message_already_naming_the_joint_is_not_prefixed_twice() -> None:
    assert str(NotHomedError("j2: something", joint="j2")) == "j2: something"


def test_error_without_joint_carries_none() -> None:
    err = StalledError("something")
    assert (err.joint, err.register) == (None, None)


def test_comm_error_with_address_is_prefixed_with_joint_and_address() -> None:
    err = CommError("PING failed", joint="j1", register=Reg.PING, address=0x11)
    assert str(err) == "j1 (0x11): PING failed"
    assert err.address == 0x11


def test_comm_error_from_a_nacking_bus_carries_joint_register_and_address() -> None:
    emu = build_emulated(J1, start_q=2.9, faults=FaultPlan(nack=1.0))
    with pytest.raises(CommError) as info:
        emu.joint.init()
    assert info.value.joint == "j1"
    assert info.value.register is Reg.PING
    assert info.value.address == J1.address


def test_not_homed_error_from_set_position_carries_the_joint() -> None:
    emu = build_emulated(J1, start_q=2.9)
    emu.joint.init()
    emu.joint.enable(20, 20)
    with pytest.raises(NotHomedError) as info:
        emu.joint.set_position(0.0)
    assert info.value.joint == "j1"
    assert info.value.register is None  # refused before any traffic
    assert str(info.value) == "j1: joint not homed; home it before moving"


def test_unknown_joint_error_is_a_config_error_and_an_invalid_argument() -> None:
    assert issubclass(UnknownJointError, ConfigError)
    assert issubclass(UnknownJointError, InvalidArgumentError)
    assert UnknownJointError("unknown joint 'j9'").code is ErrType.INVALID_ARGUMENT


def test_joint_error_defaults_to_generic_error() -> None:
    assert JointError().code is ErrType.ERROR


def test_invalid_argument_error_is_a_value_error() -> None:
    assert issubclass(InvalidArgumentError, ValueError)
    with pytest.raises(ValueError, match="j4"):
        raise InvalidArgumentError("j4: bad")


@pytest.mark.parametrize("cls", [NotHomedError, NotEnabledError, StalledError, NotInitError, CommError])
def test_state_errors_are_not_value_errors(cls: type[JointError]) -> None:
    assert not issubclass(cls, ValueError)
