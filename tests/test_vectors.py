"""The one check of vectors (`protocol.vectors`): values and the text of a flag."""

from __future__ import annotations

import re

import numpy as np
import pytest

from archery.protocol.vectors import MAX_SHOWN, finite_vector, parse_vector


class Refused(ValueError):
    """A caller's own exception class."""


def _message(name: str, size: int, unit: str) -> str:
    return re.escape(f"{name} must be a finite {size}-vector ({unit}): {size} finite numbers, got")


@pytest.mark.parametrize(
    "value",
    [[0.2, 0.0, -0.03], (0.2, 0, -0.03), np.array([0.2, 0.0, -0.03]), [np.float32(0.2), 0, -0.03]],
)
def test_a_vector_becomes_a_read_only_float_array(value: object) -> None:
    vec = finite_vector("θ", value, Refused)
    assert vec.dtype == np.float64 and vec.shape == (3,)
    np.testing.assert_allclose(vec, [0.2, 0.0, -0.03], rtol=1e-6)
    assert not vec.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        vec[0] = 1.0


def test_the_result_is_a_copy() -> None:
    given = np.array([1.0, 2.0, 3.0])
    vec = finite_vector("wind", given, Refused, unit="m/s")
    given[0] = 9.0
    assert vec.tolist() == [1.0, 2.0, 3.0] and given.flags.writeable


def test_other_sizes_and_integers() -> None:
    assert finite_vector("od", [0, 0, 1, 0], Refused, size=4, unit="rad").tolist() == [0, 0, 1, 0]
    assert finite_vector("r", np.array([1, 2]), Refused, size=2).dtype == np.float64


@pytest.mark.parametrize(
    "value",
    [
        [0.1, 0.2],
        [0.1, 0.2, 0.3, 0.4],
        [],
        np.zeros(4),
        np.zeros((1, 3)),
        [[0.1, 0.2, 0.3]],
        [[0.1], [0.2], [0.3]],
        [0.1, [0.2], 0.3],
    ],
)
def test_wrong_sizes_and_nested_lists_are_refused(value: object) -> None:
    with pytest.raises(Refused, match=_message("θ", 3, "m")):
        finite_vector("θ", value, Refused)


@pytest.mark.parametrize(
    "value",
    [
        "abc",
        "1,2",
        "123",
        b"123",
        ["1", "2", "3"],
        np.array(["1", "2", "3"]),
        None,
        3.0,
        {"x": 1, "y": 2, "z": 3},
        {1.0, 2.0, 3.0},
        np.array([1 + 0j, 2, 3]),
    ],
)
def test_strings_and_non_vectors_are_refused(value: object) -> None:
    with pytest.raises(Refused, match=_message("position", 3, "m")):
        finite_vector("position", value, Refused)


@pytest.mark.parametrize(
    "value",
    [
        True,
        [True, False, True],
        [1.0, True, 0.0],
        np.array([True, False, True]),
        [np.bool_(1), 0, 0],
    ],
)
def test_bools_are_not_numbers(value: object) -> None:
    with pytest.raises(Refused, match=_message("θ", 3, "m")):
        finite_vector("θ", value, Refused)


@pytest.mark.parametrize(
    "value",
    [
        [float("nan"), 0.0, 0.0],
        [0.0, float("inf"), 0.0],
        (0.0, 0.0, -float("inf")),
        np.array([0.0, np.nan, 0.0]),
        [10**400, 0, 0],
    ],
)
def test_nan_inf_and_overflow_are_refused(value: object) -> None:
    with pytest.raises(Refused, match=_message("wind", 3, "m/s")):
        finite_vector("wind", value, Refused, unit="m/s")


def test_the_message_names_field_size_unit_and_value() -> None:
    with pytest.raises(Refused) as info:
        finite_vector("scenario.theta0", [0.1, 0.2], Refused, unit="m")
    assert str(info.value) == (
        "scenario.theta0 must be a finite 3-vector (m): 3 finite numbers, got [0.1, 0.2]"
    )


@pytest.mark.parametrize(
    "value",
    [
        list(range(10**6)),
        np.arange(10**6, dtype=float),
        np.zeros((1000, 1000)),
        "x" * 10**7,
        ["y" * 10**6, 0.0, 0.0],
        [[[[[0.0] * 1000]]], 0.0, 0.0],
    ],
)
def test_a_huge_value_gives_a_short_one_line_message(value: object) -> None:
    with pytest.raises(Refused) as info:
        finite_vector("θ", value, Refused)
    message = str(info.value)
    prefix = "θ must be a finite 3-vector (m): 3 finite numbers, got "
    assert message.startswith(prefix)
    assert len(message) <= len(prefix) + MAX_SHOWN and "\n" not in message


@pytest.mark.parametrize("size", [0, -1, True, 3.0])
def test_a_bad_size_is_the_callers_mistake(size: object) -> None:
    with pytest.raises(ValueError, match="size must be an integer >= 1"):
        finite_vector("θ", [0.0, 0.0, 0.0], Refused, size=size)  # type: ignore[arg-type]  # a wrong size on purpose


# -- the text of a flag --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text", ["0.2,0,-0.03", "0.2, 0, -0.03", " 0.2 ,0 , -0.03 ", "2e-1,0.0,-3e-2", "+0.2,-0,-.03"]
)
def test_a_flag_gives_its_vector(text: str) -> None:
    vec = parse_vector("--theta0", text, Refused)
    np.testing.assert_allclose(vec, [0.2, 0.0, -0.03])
    assert vec.dtype == np.float64 and not vec.flags.writeable


def test_a_flag_of_another_size() -> None:
    assert parse_vector("--od", "0,0,1,0", Refused, size=4, unit="rad").tolist() == [0, 0, 1, 0]


@pytest.mark.parametrize(
    "text",
    [
        "",
        " ",
        "1,2",
        "1,2,3,4",
        "1,,3",
        "1,2,3,",
        ",1,2",
        "a,b,c",
        "1,2,x",
        "1;2;3",
        "1 2 3",
        "nan,0,0",
        "0,inf,0",
        "0,0,-inf",
        "1e400,0,0",
        "[1,2,3]",
    ],
)
def test_a_bad_flag_names_itself_and_quotes_the_text(text: str) -> None:
    with pytest.raises(Refused) as info:
        parse_vector("--wind", text, Refused, unit="m/s")
    assert str(info.value) == (
        f"--wind must be a finite 3-vector (m/s): 3 comma-separated finite numbers, got {text!r}"
    )


def test_a_flag_that_is_not_text_is_refused() -> None:
    with pytest.raises(Refused, match="--wind must be a finite 3-vector"):
        parse_vector("--wind", [1.0, 2.0, 3.0], Refused)  # type: ignore[arg-type]  # not text on purpose


def test_a_huge_flag_is_quoted_short() -> None:
    with pytest.raises(Refused) as info:
        parse_vector("--start", "1," * 10**6, Refused)
    prefix = "--start must be a finite 3-vector (m): 3 comma-separated finite numbers, got "
    assert str(info.value).startswith(prefix)
    assert len(str(info.value)) <= len(prefix) + MAX_SHOWN


def test_the_callers_exception_class_is_raised() -> None:
    class Usage(Exception):
        pass

    with pytest.raises(Usage):
        parse_vector("--theta0", "1,2", Usage)
    with pytest.raises(Usage):
        finite_vector("θ", [1, 2], Usage)
