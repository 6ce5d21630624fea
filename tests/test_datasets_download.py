"""Download helper and scripts, against a local HTTP server (no internet needed)."""

from __future__ import annotations

import hashlib
import http.server
import io
import tarfile
import threading
import zipfile
from pathlib import Path

import pytest

from scripts import download_3dmatch, download_modelnet40, download_rgbd
from scripts._download import (
    DownloadError,
    IntegrityError,
    Resource,
    download,
    extract,
    fetch,
    fetch_and_extract,
    verify,
)

PAYLOAD = bytes(range(256)) * 1200  # 307 200 bytes


class _Handler(http.server.BaseHTTPRequestHandler):
    """Serves ``server.files``; honours ``Range`` unless ``server.ranges`` is False."""

    def do_GET(self):
        self.server.requests.append((self.path, self.headers.get("Range")))
        body = self.server.files.get(self.path)
        if body is None:
            self.send_error(404)
            return
        start = 0
        header = self.headers.get("Range")
        if header and self.server.ranges:
            start = int(header.removeprefix("bytes=").split("-")[0])
            if start >= len(body):
                self.send_error(416)
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        else:
            self.send_response(200)
        self.send_header("Content-Length", str(len(body) - start))
        self.end_headers()
        sent = body[start:]
        if self.server.cut_after is not None:
            sent = sent[: self.server.cut_after]
            self.server.cut_after = None
        self.wfile.write(sent)

    def log_message(self, *args):
        """Silence the request log."""


@pytest.fixture
def server():
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    httpd.files, httpd.requests, httpd.ranges, httpd.cut_after = {}, [], True, None
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    httpd.url = f"http://127.0.0.1:{httpd.server_address[1]}"
    yield httpd
    httpd.shutdown()
    httpd.server_close()


def _resource(server, *paths: str, **checks) -> Resource:
    return Resource(name="data.bin", urls=tuple(server.url + p for p in paths), **checks)


def test_partial_download_resumes_with_a_range_request(server, tmp_path):
    server.files["/data.bin"] = PAYLOAD
    (tmp_path / "data.bin.part").write_bytes(PAYLOAD[:100_000])
    path = fetch(_resource(server, "/data.bin", sha256=hashlib.sha256(PAYLOAD).hexdigest()), tmp_path, progress=False)
    assert path.read_bytes() == PAYLOAD
    assert server.requests == [("/data.bin", "bytes=100000-")]
    assert not (tmp_path / "data.bin.part").exists()


def test_server_without_range_support_restarts_the_file(server, tmp_path):
    server.files["/data.bin"], server.ranges = PAYLOAD, False
    (tmp_path / "data.bin.part").write_bytes(b"stale bytes")
    download(server.url + "/data.bin", tmp_path / "data.bin", progress=False)
    assert (tmp_path / "data.bin").read_bytes() == PAYLOAD


def test_interrupted_transfer_keeps_the_part_file_and_resumes(server, tmp_path):
    server.files["/data.bin"], server.cut_after = PAYLOAD, 50_000
    with pytest.raises(OSError, match="connection closed after 50000 of 307200 bytes"):
        download(server.url + "/data.bin", tmp_path / "data.bin", progress=False)
    assert (tmp_path / "data.bin.part").stat().st_size == 50_000
    download(server.url + "/data.bin", tmp_path / "data.bin", progress=False)
    assert (tmp_path / "data.bin").read_bytes() == PAYLOAD
    assert server.requests[-1] == ("/data.bin", "bytes=50000-")


def test_complete_part_file_is_accepted_on_416(server, tmp_path):
    server.files["/data.bin"] = PAYLOAD
    (tmp_path / "data.bin.part").write_bytes(PAYLOAD)
    download(server.url + "/data.bin", tmp_path / "data.bin", progress=False)
    assert (tmp_path / "data.bin").read_bytes() == PAYLOAD


def test_mirrors_are_tried_in_order_and_corrupt_copies_rejected(server, tmp_path):
    server.files["/corrupt.bin"] = PAYLOAD[:-1] + b"x"
    server.files["/good.bin"] = PAYLOAD
    resource = _resource(server, "/missing.bin", "/corrupt.bin", "/good.bin", md5=hashlib.md5(PAYLOAD).hexdigest())
    assert fetch(resource, tmp_path, progress=False).read_bytes() == PAYLOAD
    assert [path for path, _ in server.requests] == ["/missing.bin", "/corrupt.bin", "/good.bin"]


def test_dead_links_give_manual_instructions(server, tmp_path):
    resource = _resource(server, "/gone.bin", size=len(PAYLOAD), md5=hashlib.md5(PAYLOAD).hexdigest())
    with pytest.raises(DownloadError) as caught:
        fetch(resource, tmp_path, progress=False)
    message = str(caught.value)
    assert "404" in message and f"{server.url}/gone.bin" in message
    assert f"put it at\n  {tmp_path / 'data.bin'}" in message
    assert f"size {len(PAYLOAD)} bytes" in message


def test_plain_http_mirrors_need_a_checksum(server, tmp_path):
    server.files["/data.bin"] = PAYLOAD
    unverifiable = _resource(server, "/data.bin", size=len(PAYLOAD))
    with pytest.raises(DownloadError, match=r"data\.bin: skipped, plain http without a published checksum"):
        fetch(unverifiable, tmp_path, progress=False)
    assert server.requests == []
    verified = _resource(server, "/data.bin", sha256=hashlib.sha256(PAYLOAD).hexdigest())
    assert fetch(verified, tmp_path, progress=False).read_bytes() == PAYLOAD


@pytest.mark.parametrize("link", ["top", "top/x.txt"])
def test_extraction_does_not_follow_links_inside_the_destination(tmp_path, link):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "x.txt").write_bytes(b"precious")
    out = tmp_path / "out"
    (out / link).parent.mkdir(parents=True, exist_ok=True)
    (out / link).symlink_to(outside if link == "top" else outside / "x.txt")
    archive = _zip(tmp_path / "a.zip", {"top/x.txt": b"overwritten"})
    with pytest.raises(ValueError, match=rf"refusing to extract 'top/x\.txt': .*{link}.* is a symbolic link"):
        extract(archive, out)
    assert (outside / "x.txt").read_bytes() == b"precious"


def test_file_placed_by_hand_is_verified_without_network(tmp_path):
    resource = Resource(name="data.bin", urls=("http://127.0.0.1:9/never",), sha256=hashlib.sha256(PAYLOAD).hexdigest())
    (tmp_path / "data.bin").write_bytes(PAYLOAD)
    assert fetch(resource, tmp_path, progress=False) == tmp_path / "data.bin"
    (tmp_path / "data.bin").write_bytes(b"truncated")
    with pytest.raises(IntegrityError, match=f"sha256 {hashlib.sha256(b'truncated').hexdigest()}, expected"):
        fetch(resource, tmp_path, progress=False)
    with pytest.raises(IntegrityError, match="size 9 bytes, expected 5"):
        verify(tmp_path / "data.bin", Resource(name="data.bin", urls=(), size=5))


def _zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as bundle:
        for name, data in members.items():
            bundle.writestr(name, data)
    return path


def test_extract_zip_and_tar_and_reject_unsafe_or_corrupt_archives(tmp_path):
    extracted = extract(_zip(tmp_path / "a.zip", {"top/x.txt": b"x", "top/sub/y.txt": b"y"}), tmp_path / "out")
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in extracted) == ["top/sub/y.txt", "top/x.txt"]
    with tarfile.open(tmp_path / "b.tgz", "w:gz") as bundle:
        info = tarfile.TarInfo("seq/depth.txt")
        info.size = 3
        bundle.addfile(info, io.BytesIO(b"abc"))
    extract(tmp_path / "b.tgz", tmp_path / "out")
    assert (tmp_path / "out" / "seq" / "depth.txt").read_bytes() == b"abc"
    with pytest.raises(ValueError, match="points outside"):
        extract(_zip(tmp_path / "evil.zip", {"../escape.txt": b"!"}), tmp_path / "out")
    assert not (tmp_path / "escape.txt").exists()
    (tmp_path / "broken.zip").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ValueError, match=r"not a zip or tar archive|corrupt archive"):
        extract(tmp_path / "broken.zip", tmp_path / "out")


def test_fetch_and_extract_checks_members_once(tmp_path):
    archive = _zip(tmp_path / "set.zip", {"set/a.h5": b"alpha"})
    good = Resource(name="set.zip", urls=(), member_md5={"set/a.h5": hashlib.md5(b"alpha").hexdigest()})
    out = fetch_and_extract(good, tmp_path, tmp_path / "data", progress=False)
    assert (out / "set" / "a.h5").read_bytes() == b"alpha"
    archive.unlink()
    assert fetch_and_extract(good, tmp_path, tmp_path / "data", progress=False) == out
    _zip(tmp_path / "set.zip", {"set/a.h5": b"beta"})
    bad = Resource(name="set.zip", urls=(), member_md5={"set/a.h5": hashlib.md5(b"alpha").hexdigest()})
    with pytest.raises(IntegrityError, match=r"a\.h5: md5"):
        fetch_and_extract(bad, tmp_path, tmp_path / "other", progress=False)


def test_modelnet_script_lists_mirrors_and_uses_a_placed_archive(tmp_path, capsys):
    assert download_modelnet40.main(["--list"]) == 0
    listing = capsys.readouterr().out
    assert "huggingface.co/datasets/Msun/modelnet40" in listing and "3176385ffc31a7b6b5af22191fd920d1" not in listing
    assert "md5 of 7 extracted files" in listing
    _zip(
        tmp_path / "modelnet40_normal_resampled.zip",
        {"modelnet40_normal_resampled/airplane/airplane_0001.txt": b"0,0,0,0,0,1\n"},
    )
    assert download_modelnet40.main(["--root", str(tmp_path), "--format", "resampled", "--quiet"]) == 0
    assert (tmp_path / "modelnet40_normal_resampled" / "airplane" / "airplane_0001.txt").is_file()
    assert "name: modelnet40" in capsys.readouterr().out
    _zip(tmp_path / "modelnet40_ply_hdf5_2048.zip", {"modelnet40_ply_hdf5_2048/ply_data_train0.h5": b"fake"})
    assert download_modelnet40.main(["--root", str(tmp_path), "--format", "hdf5", "--quiet"]) == 1
    assert "md5" in capsys.readouterr().err


def test_3dmatch_and_rgbd_scripts_describe_their_sources(tmp_path, capsys):
    assert download_3dmatch.main(["--list", "--scenes", "7-scenes-redkitchen"]) == 0
    listing = capsys.readouterr().out
    assert "scene-fragments/7-scenes-redkitchen-evaluation.zip" in listing
    assert "3DLoMatch/7-scenes-redkitchen/gt_overlap.log" in listing
    assert download_rgbd.main(["--list", "--dataset", "7scenes", "--scenes", "heads"]) == 0
    listing = capsys.readouterr().out
    assert "28564B23-0828-408F-8631-23B1EFF1DAC8/heads.zip" in listing and "956332240" in listing
    assert download_rgbd.main(["--list", "--dataset", "tum", "--scenes", "freiburg1_xyz"]) == 0
    assert "freiburg1/rgbd_dataset_freiburg1_xyz.tgz" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        download_rgbd.main(["--dataset", "tum", "--scenes", "freiburg9_nowhere"])
    assert "unknown tum name(s) ['freiburg9_nowhere']" in capsys.readouterr().err


def test_seven_scenes_inner_sequence_archives_are_extracted(tmp_path):
    scene = tmp_path / "heads"
    scene.mkdir()
    _zip(scene / "seq-01.zip", {"seq-01/frame-000000.pose.txt": b"1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"})
    assert download_rgbd.extract_sequences(scene) == [scene / "seq-01"]
    assert (scene / "seq-01" / "frame-000000.pose.txt").is_file()
