"""RAW header parsing (current and legacy headers), format / geometry inference, the header writer."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from labrig.devices.raw import RawFormatError, make_header, parse_header, read_header, read_raw, write_raw

DATA = Path(os.environ.get("LABRIG_EVT_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "evt"))
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real RAW samples not found at {DATA} (set LABRIG_EVT_DATA)")


def test_evk4_header_fields_end_and_payload_offset() -> None:
    head = b"% camera_integrator_name Prophesee\n% date 2023-03-29 16:37:46\n% evt 3.0\n% format EVT3;height=720;width=1280\n"
    head += b"% geometry 1280x720\n% plugin_name hal_plugin_imx636_evk4\n% system_ID 49\n% end\n"
    h = parse_header(head + b"% \x00\x80")  # payload bytes that look like a header line after % end
    assert h.has_end and h.size == len(head)
    assert h.fields["date"] == "2023-03-29 16:37:46"  # value with a space
    assert h.format_name() == "EVT3" and h.geometry() == (1280, 720)
    assert h.text == head.decode()


def test_legacy_header_stops_at_first_non_header_byte() -> None:
    head = b"% Date 2020-09-25 07:48:29\n% evt 3.0\n% plugin_name hal_plugin_gen41_evk3\n% system_ID 48\n"
    h = parse_header(head + b"-\x8b\x00\x60")
    assert not h.has_end and h.size == len(head)
    assert h.fields == {"Date": "2020-09-25 07:48:29", "evt": "3.0", "plugin_name": "hal_plugin_gen41_evk3", "system_ID": "48"}
    assert h.format_name() == "EVT3" and h.geometry() == (1280, 720)
    # '%' without a space does not begin a header line
    assert parse_header(b"%evt 3.0\n").size == 0
    assert parse_header(b"").size == 0


@pytest.mark.parametrize(
    ("fields", "fmt", "geometry"),
    [
        ({"system_ID": "21"}, "EVT2", (640, 480)),  # Gen3.0
        ({"system_ID": "48", "evt": "2.0"}, "EVT2", (1280, 720)),  # evt key wins over the system's format
        ({"system_ID": "0x31"}, "EVT3", (1280, 720)),  # EVK4 (IMX636)
        ({"evt": "3.0", "sensor_generation": "4.2"}, "EVT3", (1280, 720)),
        ({"evt": "3.0", "generation": "3.1"}, "EVT3", (640, 480)),
        ({"evt": "2.0", "plugin_name": "hal_plugin_gen3_fx3"}, "EVT2", (640, 480)),
        ({"evt": "3.0", "plugin_name": "hal_plugin_imx636_evk4"}, "EVT3", (1280, 720)),
        ({"format": "EVT3;height=320;width=320"}, "EVT3", (320, 320)),
        ({"format": "EVT2", "geometry": "304x240"}, "EVT2", (304, 240)),
        ({"evt": "3.0"}, "EVT3", None),
        ({"serial_number": "1"}, None, None),
    ],
)
def test_format_and_geometry_inference(fields: dict[str, str], fmt: str | None, geometry: tuple[int, int] | None) -> None:
    head = "".join(f"% {k} {v}\n" for k, v in fields.items()).encode()
    h = parse_header(head)
    assert h.format_name() == fmt
    assert h.geometry() == geometry


@needs_data
@pytest.mark.parametrize(
    ("name", "fmt", "geometry"), [("evt3_sample.raw", "EVT3", (1280, 720)), ("evt2_sample.raw", "EVT2", (640, 480))]
)
def test_real_legacy_headers(name: str, fmt: str, geometry: tuple[int, int]) -> None:
    h = read_header(str(DATA / name))
    assert not h.has_end and "format" not in h.fields and "geometry" not in h.fields
    assert h.format_name() == fmt and h.geometry() == geometry
    assert (DATA / name).read_bytes()[h.size : h.size + 1] != b"%"


def test_make_header_is_sorted_evk4_like_and_ends() -> None:
    text = make_header("EVT3", 1280, 720, {"serial_number": "00ca0009"}).decode()
    lines = text.splitlines()
    assert lines[-1] == "% end"
    keys = [line.split()[1] for line in lines[:-1]]
    assert keys == sorted(keys)
    assert "% format EVT3;height=720;width=1280" in lines
    assert "% evt 3.0" in lines and "% geometry 1280x720" in lines and "% system_ID 49" in lines
    assert "% serial_number 00ca0009" in lines and "% plugin_name hal_plugin_imx636_evk4" in lines
    h = parse_header(text.encode())
    assert h.has_end and h.format_name() == "EVT3" and h.geometry() == (1280, 720)
    two = parse_header(make_header("EVT2", 640, 480))
    assert two.fields["evt"] == "2.0" and two.format_name() == "EVT2" and two.geometry() == (640, 480)
    with pytest.raises(ValueError):
        make_header("EVT21", 1, 1)
    with pytest.raises(ValueError):
        make_header("EVT3", 1, 1, {"bad key": "x"})


def test_read_raw_without_format_needs_one(tmp_path: Path) -> None:
    path = tmp_path / "noformat.raw"
    path.write_bytes(b"% serial_number 1\n\x00\x80\x00\x60")
    with pytest.raises(RawFormatError):
        read_raw(path)
    raw = read_raw(path, format="EVT3")
    assert raw.format == "EVT3" and raw.geometry is None and raw.events.size == 0


def test_header_only_and_empty_files(tmp_path: Path) -> None:
    path = tmp_path / "empty.raw"
    write_raw(path, np.zeros(0, [("x", "u2"), ("y", "u2"), ("p", "u1"), ("t", "i8")]))
    raw = read_raw(path)
    assert raw.header.has_end and raw.events.size == 0 and raw.skipped_words == 0
    (tmp_path / "zero.raw").write_bytes(b"")
    assert read_raw(tmp_path / "zero.raw", format="EVT2").events.size == 0
