"""Download with cache, resume, atomic rename and integrity checks, against a loopback HTTP server."""

from __future__ import annotations

import http.server
import threading
from pathlib import Path

import pytest

from spoil_torchrl.data import DatasetError, download, load_episodes, sha256_of, write_dsrl_file
from spoil_torchrl.data import load as load_module
from spoil_torchrl.tasks import get_dsrl_dataset
from tests.data.helpers import make_arrays


class _Handler(http.server.BaseHTTPRequestHandler):
    files: dict[str, bytes] = {}
    honour_range = True
    fail_after: int | None = None  # close the connection after this many body bytes
    requests: list[dict] = []

    def log_message(self, *args):  # keep test output clean
        pass

    def do_GET(self):  # noqa: N802 - http.server API
        body = self.files.get(self.path)
        self.requests.append({"path": self.path, "range": self.headers.get("Range")})
        if body is None:
            self.send_error(404)
            return
        start = 0
        ranged = self.headers.get("Range")
        if ranged and self.honour_range:
            start = int(ranged.split("=")[1].split("-")[0])
            if start >= len(body):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(body)}")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        else:
            self.send_response(200)
        payload = body[start:]
        self.send_header("Content-Length", str(len(payload)))
        self.end_headers()
        if self.fail_after is not None:
            payload = payload[: self.fail_after]
        self.wfile.write(payload)


@pytest.fixture
def server():
    _Handler.files, _Handler.honour_range, _Handler.fail_after, _Handler.requests = {}, True, None, []
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}", _Handler
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture
def hdf5_bytes(tmp_path) -> bytes:
    path = write_dsrl_file(tmp_path / "src.hdf5", make_arrays(lengths=(50, 50), ends=("timeout", "timeout")))
    return path.read_bytes()


def test_download_checks_and_renames_atomically(server, hdf5_bytes, tmp_path):
    url, handler = server
    handler.files["/d.hdf5"] = hdf5_bytes
    dest = tmp_path / "cache" / "d.hdf5"
    out = download(f"{url}/d.hdf5", dest, sha256=sha256_of_bytes(hdf5_bytes), progress=False)
    assert out == dest and dest.read_bytes() == hdf5_bytes
    assert not dest.with_name("d.hdf5.part").exists()
    download(f"{url}/d.hdf5", dest, progress=False)  # cached: no second request
    assert len(handler.requests) == 1


def sha256_of_bytes(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()


def test_interrupted_download_resumes_with_a_range_request(server, hdf5_bytes, tmp_path):
    url, handler = server
    handler.files["/d.hdf5"] = hdf5_bytes
    dest = tmp_path / "d.hdf5"
    handler.fail_after = len(hdf5_bytes) // 3
    with pytest.raises(DatasetError, match="run again to resume"):
        download(f"{url}/d.hdf5", dest, progress=False)
    part = dest.with_name("d.hdf5.part")
    assert part.stat().st_size == len(hdf5_bytes) // 3 and not dest.exists()
    handler.fail_after = None
    download(f"{url}/d.hdf5", dest, progress=False)
    assert handler.requests[-1]["range"] == f"bytes={len(hdf5_bytes) // 3}-"
    assert dest.read_bytes() == hdf5_bytes


def test_server_ignoring_range_restarts_from_zero(server, hdf5_bytes, tmp_path):
    url, handler = server
    handler.files["/d.hdf5"] = hdf5_bytes
    handler.honour_range = False
    dest = tmp_path / "d.hdf5"
    dest.with_name("d.hdf5.part").write_bytes(b"garbage")
    download(f"{url}/d.hdf5", dest, progress=False)
    assert dest.read_bytes() == hdf5_bytes


def test_checksum_or_validation_failure_deletes_the_download(server, hdf5_bytes, tmp_path):
    url, handler = server
    handler.files["/d.hdf5"] = hdf5_bytes
    handler.files["/page.hdf5"] = b"<html>moved</html>"
    dest = tmp_path / "d.hdf5"
    with pytest.raises(DatasetError, match="SHA-256 mismatch"):
        download(f"{url}/d.hdf5", dest, sha256="0" * 64, progress=False)
    assert not dest.exists() and not dest.with_name("d.hdf5.part").exists()
    bad = tmp_path / "page.hdf5"
    with pytest.raises(DatasetError, match="not an HDF5 file"):
        download(f"{url}/page.hdf5", bad, validate=load_module._check_hdf5, progress=False)
    assert not bad.exists() and not bad.with_name("page.hdf5.part").exists()


def test_offline_error_names_url_and_destination(tmp_path):
    dest = tmp_path / "x.hdf5"
    with pytest.raises(DatasetError) as info:
        download("http://127.0.0.1:9/x.hdf5", dest, timeout=2, progress=False)
    assert "http://127.0.0.1:9/x.hdf5" in str(info.value) and str(dest) in str(info.value)


def test_dsrl_source_downloads_into_the_cache(server, tmp_path, monkeypatch):
    url, handler = server
    dataset = get_dsrl_dataset("OfflinePointCircle1Gymnasium-v0")
    src = write_dsrl_file(tmp_path / "src.hdf5", make_arrays(obs_dim=28, act_dim=2))
    handler.files[f"/{dataset.file_name}"] = src.read_bytes()
    monkeypatch.setattr("spoil_torchrl.tasks.DSRL_BASE_URL", f"{url}/")
    monkeypatch.setenv("DSRL_DATASET_DIR", str(tmp_path / "dsrl"))
    td = load_episodes(f"dsrl:{dataset.dataset_id}", progress=False)
    assert td.shape == (9,)
    assert (tmp_path / "dsrl" / dataset.file_name).exists()
    assert sha256_of(tmp_path / "dsrl" / dataset.file_name) == sha256_of(src)


def test_missing_remote_file_is_a_clear_error(server, tmp_path):
    url, _ = server
    with pytest.raises(DatasetError, match="HTTP 404.*place the file at"):
        download(f"{url}/none.hdf5", tmp_path / "none.hdf5", progress=False)
    assert not Path(tmp_path / "none.hdf5").exists()
