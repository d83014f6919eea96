"""Config fields that are also flags: one declaration gives the flag, its help, the parsed config
and the checks of a config built in code."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from archery.mesh.cliargs import ArgumentParser
from archery.mesh.configflags import add_config_args, check_bounds, config_from_args, flag
from archery.protocol.errors import ConfigError


def _parse_pair(text: str) -> tuple[int, int]:
    a, _, b = text.partition(",")
    if not (a.isdigit() and b.isdigit()):
        raise ConfigError(f"--pair {text!r} is not A,B")
    return int(a), int(b)


@dataclass(frozen=True)
class Settings:
    label: str = "fixed"
    state_rate: float = flag(50.0, "states per s", unit="Hz", low=0.1, high=1000)
    wait: float = flag(10.0, "longest wait", unit="s", low=0, high=60, low_open=True)
    seed: int | None = flag(0, "seed", low=0)
    mode: str = flag("fast", "how", choices=("fast", "slow"))
    report: bool = flag(True, "write no report", name="--no-report")
    pair: tuple[int, int] = flag((1, 2), "two numbers", parse=_parse_pair, metavar="A,B")
    out: Path = flag("runs", "folder")
    width: int = flag(64, "width", unit="px", low=16, high=4096, name="--size", cli=False)

    def __post_init__(self) -> None:
        check_bounds(self)


def _parser() -> ArgumentParser:
    parser = ArgumentParser(prog="archery test")
    add_config_args(parser, Settings)
    return parser


def test_flags_come_from_the_fields_with_their_defaults() -> None:
    args = _parser().parse_args([])
    config = config_from_args(Settings, args, label="given")
    assert config == Settings(label="given")
    assert isinstance(config.out, Path) and config.out == Path("runs")
    args = _parser().parse_args(
        ["--state-rate", "20", "--seed", "7", "--mode", "slow", "--no-report", "--pair", "3,4"]
    )
    config = config_from_args(Settings, args)
    assert (config.state_rate, config.seed, config.mode) == (20.0, 7, "slow")
    assert config.report is False and config.pair == (3, 4)
    assert not hasattr(args, "width")  # checked, but set by another flag


def test_help_states_unit_range_and_default() -> None:
    text = _parser().format_help()
    assert "states per s (Hz; 0.1..1000; default 50)" in text
    assert "longest wait (s; (0, 60]; default 10)" in text
    assert "--no-report" in text and "--size" not in text


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"state_rate": 0.0}, r"--state-rate must be in \[0.1, 1000\] Hz, got 0.0"),
        ({"state_rate": float("nan")}, r"--state-rate must be a finite number Hz, got nan"),
        ({"wait": 0}, r"--wait must be in \(0, 60\] s, got 0"),
        ({"seed": -1}, r"--seed must be an integer >= 0, got -1"),
        ({"seed": True}, r"--seed must be an integer >= 0, got True"),
        ({"width": 8}, r"--size must be an integer in \[16, 4096\] px, got 8"),
        ({"mode": "medium"}, r"--mode 'medium' is not one of fast, slow"),
        ({"report": "yes"}, r"report must be true or false, got 'yes'"),
        ({"label": 3}, r"label must be a str, got 3"),
    ],
)
def test_a_config_built_in_code_is_checked_like_one_from_flags(
    overrides: dict[str, object], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        Settings(**overrides)  # type: ignore[arg-type]  # bad values on purpose


def test_none_is_valid_for_an_optional_field_and_parse_errors_name_the_flag() -> None:
    assert Settings(seed=None).seed is None
    args = _parser().parse_args(["--pair", "x"])
    with pytest.raises(ConfigError, match="--pair 'x' is not A,B"):
        config_from_args(Settings, args)
