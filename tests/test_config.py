"""`Settings`: defaults, validation, the environment and flags, and `isosr serve`'s options."""

from __future__ import annotations

import logging
import sys

import pytest

from isosr_cli.main import build_parser, main
from isosr_cli.serve_cmd import REPLICA_FLAGS
from isosr_net.inference import default_precision
from isosr_server.core.config import TOKEN_ENV, Settings, configure_process, options

TOKEN = "correct-horse-battery"


def serve_parser():
    return build_parser()._subparsers._group_actions[0].choices["serve"]


def test_precision_defaults_by_device():
    assert [default_precision(d) for d in ("cpu", "cuda", "cuda:1")] == ["fp32", "fp16", "fp16"]
    assert Settings(device="cuda:0").resolved_precision == "fp16"
    assert Settings(device="cuda", precision="bf16").resolved_precision == "bf16"
    assert Settings().precision is None and Settings().resolved_precision == "fp32"


def test_token_required_beyond_loopback():
    with pytest.raises(ValueError, match="--token"):
        Settings(host="0.0.0.0")
    assert Settings(host="0.0.0.0", token=TOKEN, insecure=True).token == TOKEN  # TLS: tests/test_tls.py
    with pytest.raises(ValueError, match="at least 8"):
        Settings(token="short")


@pytest.mark.parametrize("bad, words", [({"precision": "fp8"}, "precision"), ({"log_level": "loud"}, "log_level"),
                                        ({"port": 70000}, "port"), ({"target_fps": 0.0}, "target_fps"),
                                        ({"switch_interval_ms": 0.0}, "switch_interval_ms"),
                                        ({"switch_interval_ms": float("nan")}, "switch_interval_ms"),
                                        ({"switch_interval_ms": 1e300}, r"switch_interval_ms must lie in \(0, 1000\]")])
def test_bad_settings_are_refused(bad, words):
    with pytest.raises(ValueError, match=words):
        Settings(**bad)


def test_a_server_process_takes_its_switch_interval_and_log_level(monkeypatch):
    """configure_process: the interpreter lock's switch interval from the settings (the flag over the environment,
    1 ms by default where Python's is 5), isosr's log level."""
    monkeypatch.setattr(sys, "setswitchinterval", lambda s: set_to.append(s))
    monkeypatch.setattr(logging.getLogger("isosr"), "level", logging.getLogger("isosr").level)
    set_to = []
    configure_process(Settings())
    configure_process(Settings.from_args(serve_parser().parse_args(["--switch-interval-ms", "0.5", "--log-level",
                                                                    "debug"]), {"ISOSR_SWITCH_INTERVAL_MS": "2"}))
    assert logging.getLogger("isosr").level == logging.DEBUG
    configure_process(Settings.from_env({"ISOSR_SWITCH_INTERVAL_MS": "2"}))
    assert set_to == [0.001, 0.0005, 0.002]
    assert logging.getLogger("isosr").level == logging.INFO


def test_environment_then_flags():
    env = {TOKEN_ENV: TOKEN, "ISOSR_HOST": "0.0.0.0", "ISOSR_INSECURE": "1", "ISOSR_PORT": "9000",
           "ISOSR_MAX_FPS": "12.5", "ISOSR_DEVICE": ""}
    s = Settings.from_env(env)
    assert (s.token, s.host, s.port, s.limits.max_fps, s.device) == (TOKEN, "0.0.0.0", 9000, 12.5, "cpu")
    args = serve_parser().parse_args(["--port", "9001", "--max-sessions", "3"])
    s = Settings.from_args(args, env)
    assert (s.port, s.limits.max_sessions, s.limits.max_fps, s.token) == (9001, 3, 12.5, TOKEN)
    with pytest.raises(ValueError, match="ISOSR_PORT"):
        Settings.from_env({"ISOSR_PORT": "eighty"})


def test_serve_help_says_each_default_once(capsys):
    with pytest.raises(SystemExit):
        main(["serve", "--help"])
    text = capsys.readouterr().out
    assert "(default: None)" not in text and "ISOSR_TOKEN" in text
    flags = {a.option_strings[0]: a.help for a in serve_parser()._actions if a.option_strings[0] != "-h"}
    assert sorted(flags) == sorted([o.flag for o in options()] + list(REPLICA_FLAGS))
    assert all(h.count("default:") == 1 for h in flags.values()), flags


def test_serve_command_refuses_an_open_host_without_token(capsys, monkeypatch):
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    assert main(["serve", "--host", "0.0.0.0", "--max-fps", "30"]) == 2
    assert "--token" in capsys.readouterr().err
