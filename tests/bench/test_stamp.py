"""bench.stamp: results carry the id of the checkpoint that made them, and a restamp replaces it."""

from __future__ import annotations

import hashlib
import json

from bench.stamp import checkpoint_id, main


def test_stamps_json_and_markdown_and_restamps(tmp_path):
    ckpt = tmp_path / "m.pt"
    ckpt.write_bytes(b"weights")
    cid = hashlib.sha256(b"weights").hexdigest()[:12]
    assert checkpoint_id(ckpt) == cid
    js, md = tmp_path / "r.json", tmp_path / "r.md"
    js.write_text(json.dumps({"avg_rmse": 0.01}))
    md.write_text("# Result\n\nbody\n")
    assert main([str(ckpt), str(js), str(md)]) == 0
    assert json.loads(js.read_text()) == {"checkpoint": "m.pt", "checkpoint_id": cid, "avg_rmse": 0.01}
    assert md.read_text().splitlines()[:3] == ["# Result", f"_Made with checkpoint `m.pt` (id `{cid}`)._", ""]
    ckpt.write_bytes(b"other weights")
    assert main([str(ckpt), str(js), str(md)]) == 0
    other = hashlib.sha256(b"other weights").hexdigest()[:12]
    assert json.loads(js.read_text())["checkpoint_id"] == other
    assert md.read_text().count("_Made with checkpoint") == 1 and other in md.read_text()
