"""Error codes and exceptions (SPEC.md "The host driver's rules", error codes)."""

from __future__ import annotations

import pytest

from bioscara_gym.hardware.errors import (
    CommError,
    ErrType,
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
    NotInitError,
    StalledError,
    error_for_code,
    error_to_string,
)

# SPEC.md: OK 0, ERROR -1, NOT_HOMED -2, NOT_ENABLED -3, STALLED -4,
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


@pytest.mark.parametrize(("cls", "code"), SUBCLASSES)
def test_error_for_code_builds_the_matching_subclass(cls: type[JointError], code: ErrType) -> None:
    err = error_for_code(code, "j2: message")
    assert type(err) is cls
    assert str(err) == "j2: message"


def test_error_for_generic_code_is_a_joint_error_with_that_code() -> None:
    err = error_for_code(ErrType.ERROR, "j3: boom")
    assert type(err) is JointError
    assert err.code is ErrType.ERROR


def test_joint_error_defaults_to_generic_error() -> None:
    assert JointError().code is ErrType.ERROR


def test_invalid_argument_error_is_a_value_error() -> None:
    assert issubclass(InvalidArgumentError, ValueError)
    with pytest.raises(ValueError, match="j4"):
        raise InvalidArgumentError("j4: bad")


@pytest.mark.parametrize("cls", [NotHomedError, NotEnabledError, StalledError, NotInitError, CommError])
def test_state_errors_are_not_value_errors(cls: type[JointError]) -> None:
    assert not issubclass(cls, ValueError)
