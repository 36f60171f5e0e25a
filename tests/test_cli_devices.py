"""`labrig cnc ...` and `labrig ft` against the device twins on pseudo-terminals."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from labrig.cli.devices import add_device_commands
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
from labrig.sim.grbl_twin import GrblTwin
from labrig.sim.serial_pty import TwinServer

HOMED = {110: 6000, 111: 6000, 112: 3000, 120: 1000, 121: 1000, 122: 1000, 22: 1, 20: 1, 24: 1000, 25: 3000, 27: 0.5}

app = typer.Typer()
add_device_commands(app)
runner = CliRunner()

# The main app with the two lines its owner adds, run as a user would (user errors: one line, exit 2).
MOUNTED = "from labrig import cli; from labrig.cli.devices import add_device_commands; add_device_commands(cli.app); cli.main()"


def run(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, list(args), catch_exceptions=False)
    return result.exit_code, result.stdout


@pytest.fixture
def cnc_port() -> Iterator[str]:
    twin = GrblTwin(settings=HOMED, power_on_physical_mm=(-2.0, -2.0, -1.0))
    with TwinServer({"grbl": twin}) as server:
        yield server.paths["grbl"]
        assert server.error is None


def test_cnc_status_unlock_home_move_jog_send(cnc_port: str) -> None:
    code, out = run("cnc", "--port", cnc_port, "status", "--json")
    assert code == 0 and json.loads(out)["state"] == "Alarm"  # homing enabled: Alarm at power-on
    code, out = run("cnc", "--port", cnc_port, "unlock", "--json")
    assert code == 0 and json.loads(out)["state"] == "Idle"
    code, out = run("cnc", "--port", cnc_port, "home", "--json")
    homed = json.loads(out)
    assert code == 0 and homed["state"] == "Idle" and homed["errors"] == []
    code, out = run("cnc", "--port", cnc_port, "move", "-5,-4,-2", "--feed", "3000", "--json")
    moved = json.loads(out)
    assert code == 0 and moved["state"] == "Idle" and moved["position_mm"] == pytest.approx([-5, -4, -2], abs=1e-3)
    code, out = run("cnc", "--port", cnc_port, "move", "1,,", "--relative")  # text output; Y, Z kept
    assert code == 0 and "X -4.000  Y -4.000  Z -2.000" in out
    code, out = run("cnc", "--port", cnc_port, "jog", ",,0.5", "--feed", "600", "--json")
    assert code == 0 and json.loads(out)["position_mm"] == pytest.approx([-4, -4, -1.5], abs=1e-3)
    code, out = run("cnc", "--port", cnc_port, "send", "$G", "--json")
    sent = json.loads(out)
    assert code == 0 and sent["response"][-1] == "ok" and "G90" in sent["response"][0]  # --relative restored G90
    code, out = run("cnc", "--port", cnc_port, "send", "G5", "--json")
    assert code == 1 and json.loads(out)["errors"][0]["code"] == 20


def test_cnc_stream_reports_errors_with_meaning_and_line_number(cnc_port: str, tmp_path: Path) -> None:
    program = tmp_path / "square.gcode"
    program.write_text("; a square\nG21 G90\n\nG1 X-10 Y-10 F3000\nG5\nG1 X-20\nG1 Y-20\nG1 X-10\nG1 Y-10 Q1\nG0 X-1 Y-1\n")
    assert run("cnc", "--port", cnc_port, "unlock")[0] == 0

    # One line at a time stops right at the error (counting may already have sent the lines after it).
    code, out = run("cnc", "--port", cnc_port, "stream", str(program), "--send-response", "--json")
    result = json.loads(out)
    assert code == 1 and result["stopped_early"] and result["lines_sent"] == 3 and len(result["errors"]) == 1
    first = result["errors"][0]
    assert (first["line_number"], first["code"], first["line"]) == (5, 20, "G5") and "unsupported" in first["meaning"].lower()

    code, out = run("cnc", "--port", cnc_port, "stream", str(program), "--keep-going", "--json")
    result = json.loads(out)
    assert code == 1 and not result["stopped_early"] and result["lines_sent"] == result["lines_total"] == 8
    assert [(e["line_number"], e["code"]) for e in result["errors"]] == [(5, 20), (9, 20)]
    assert result["state"] == "Idle" and result["position_mm"] == pytest.approx([-1, -1, 0], abs=1e-3)
    assert result["duration_s"] > 0 and result["lines_per_s"] > 0

    good = tmp_path / "good.gcode"
    good.write_text("".join(f"G1 X-{1 + i * 0.1:.1f} F6000\n" for i in range(40)))
    result = runner.invoke(app, ["cnc", "--port", cnc_port, "stream", str(good)], catch_exceptions=False)
    assert result.exit_code == 0 and "40/40 lines sent, 0 error(s)" in result.stdout


def test_ft_tare_json_at_800_hz() -> None:
    twin = BotaTwin(BotaTwinParams(boot_delay_us=50_000))
    with TwinServer({"ft": twin}) as server:
        deadline = time.monotonic() + 3
        while twin.mode != "run":  # powered up before the host connects
            assert time.monotonic() < deadline
            time.sleep(0.005)
        code, out = run("ft", "--port", server.paths["ft"], "--seconds", "1", "--tare", "--json")
        assert server.error is None
    result = json.loads(out)
    assert code == 0 and result["tared"]
    assert result["rate_hz"] == pytest.approx(800, rel=0.03) and 760 <= result["samples"] <= 840
    assert result["frames_lost"] == 0 and result["crc_errors"] == 0
    assert abs(result["fz_mean_n"]) < 0.02 and 0 < result["fz_std_n"] < 0.1  # tare removed the bias, noise remains
    assert {f"{a}_{s}_nm" for a in ("tx", "ty", "tz") for s in ("mean", "std", "min", "max")} <= set(result)
    assert set(result["status_counts"]) >= {"overrange", "invalid_measurements"} and not any(result["status_counts"].values())


@pytest.mark.parametrize("args", [["cnc", "--port", "/dev/labrig-no-such-port", "status"],
                                  ["ft", "--port", "/dev/labrig-no-such-port", "--seconds", "0.1"]])
def test_bad_port_is_one_line_and_exit_2(args: list[str]) -> None:
    done = subprocess.run([sys.executable, "-c", MOUNTED, *args], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert "/dev/labrig-no-such-port" in lines[0] and "labrig devices" in lines[0]
