"""`hil data emps`: local copies first, else a checksummed download into the cache.

No internet here: the download path runs against an HTTP server on 127.0.0.1 that
serves the ../shared copies (and a corrupted copy for the checksum error).
"""

from __future__ import annotations

import functools
import http.server
import shutil
import threading
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hilstack.calibration.emps import EMPS_SHA256, DataError, DataNotFound, fetch_emps
from hilstack.tools.cli import app


@pytest.fixture
def serve():
    """serve(directory) -> base URL; records the paths requested."""
    servers = []

    def start(directory: Path) -> tuple[str, list[str]]:
        requested: list[str] = []

        class Handler(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *a):  # keep the test output clean
                pass

            def do_GET(self):
                requested.append(self.path)
                super().do_GET()

        srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(directory)))
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        servers.append(srv)
        return f"http://127.0.0.1:{srv.server_address[1]}/data/", requested

    yield start
    for s in servers:
        s.shutdown()
        s.server_close()


def mirror(tmp_path: Path, src: Path, corrupt: str | None = None) -> Path:
    root = tmp_path / "www"
    (root / "data").mkdir(parents=True)
    for name in EMPS_SHA256:
        shutil.copy(src / name, root / "data" / name)
    if corrupt:
        p = root / "data" / corrupt
        b = bytearray(p.read_bytes())
        b[1000] ^= 0xFF
        p.write_bytes(bytes(b))
    return root


def test_download_checks_and_caches(tmp_path, serve, emps_dir):
    url, requested = serve(mirror(tmp_path, emps_dir))
    cache = tmp_path / "cache"
    d = fetch_emps(base_url=url, search_dirs=[cache], cache_dir=cache)
    assert d == cache and sorted(p.name for p in cache.glob("*.mat")) == sorted(EMPS_SHA256)
    assert sorted(requested) == sorted(f"/data/{n}" for n in EMPS_SHA256)
    for name in EMPS_SHA256:
        assert (cache / name).read_bytes() == (emps_dir / name).read_bytes()
    # second time: from the cache, no request
    assert fetch_emps(base_url=url, search_dirs=[cache], cache_dir=cache) == cache
    assert len(requested) == 2


def test_a_checksum_mismatch_is_an_error_and_nothing_is_kept(tmp_path, serve, emps_dir):
    url, _ = serve(mirror(tmp_path, emps_dir, corrupt="DATA_EMPS_PULSES.mat"))
    cache = tmp_path / "cache"
    with pytest.raises(DataError, match="DATA_EMPS_PULSES.mat from http://127.0.0.1:.* failed its checksum"):
        fetch_emps(base_url=url, search_dirs=[cache], cache_dir=cache)
    assert not (cache / "DATA_EMPS_PULSES.mat").exists()


def test_unreachable_server_is_one_clear_error(tmp_path):
    cache = tmp_path / "cache"
    with pytest.raises(DataError, match=r"cannot download http://127.0.0.1:9/DATA_EMPS.mat.*HIL_DATA"):
        fetch_emps(base_url="http://127.0.0.1:9/", search_dirs=[cache], cache_dir=cache)


def test_offline_uses_hil_data_and_rejects_a_corrupt_copy(tmp_path, monkeypatch, emps_dir):
    data = tmp_path / "hil_data"
    (data / "emps").mkdir(parents=True)
    for name in EMPS_SHA256:
        (data / "emps" / name).symlink_to(emps_dir / name)
    monkeypatch.setenv("HIL_DATA", str(data))
    monkeypatch.setenv("HILSTACK_CACHE", str(tmp_path / "cache"))
    assert fetch_emps(offline=True) == data / "emps"

    bad = tmp_path / "bad"
    bad.mkdir()
    for name in EMPS_SHA256:
        (bad / name).write_bytes(b"not the data")
    with pytest.raises(DataNotFound, match=r"checksum mismatch.*\$HIL_DATA/emps"):
        fetch_emps(offline=True, search_dirs=[bad])


def test_cli_converts_the_local_copy_and_exit_codes(tmp_path, monkeypatch, emps_dir):
    hil_data = tmp_path / "hil_data"
    hil_data.mkdir()
    (hil_data / "emps").symlink_to(emps_dir)
    monkeypatch.setenv("HIL_DATA", str(hil_data))
    out = tmp_path / "emps.csv"
    r = CliRunner().invoke(app, ["data", "emps", "--offline", "--csv", str(out)])
    assert r.exit_code == 0, r.output
    assert out.read_text().splitlines()[0] == "time,volts,position,reference"
    assert len(out.read_text().splitlines()) == 24841 + 1

    monkeypatch.setenv("HIL_DATA", str(tmp_path / "nothing"))
    monkeypatch.setenv("HILSTACK_CACHE", str(tmp_path / "cache"))
    import hilstack.calibration.emps as emps

    monkeypatch.setattr(emps, "emps_search_dirs", lambda: [tmp_path / "nothing" / "emps", tmp_path / "cache"])
    r = CliRunner().invoke(app, ["data", "emps", "--offline"])
    assert r.exit_code == 2 and r.output.startswith("error: EMPS data not found offline"), r.output
    r = CliRunner().invoke(app, ["data", "emps", "--url", "http://127.0.0.1:9/"])
    assert r.exit_code == 1 and r.output.count("\n") == 1 and "cannot download" in r.output, r.output
