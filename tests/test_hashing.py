"""splattwin.hashing: the digest cache read as an untrusted file."""

from __future__ import annotations

import json
import logging

from splattwin.hashing import DigestCache, sha256_file


def test_digest_cache_round_trip_and_a_cache_over_the_record_limit_is_not_read(tmp_path, monkeypatch, caplog):
    """A twin's .splattwin/digests.json may be someone else's: it is read within the record limit (before, whole,
    whatever its size); one over the limit, or one that is not JSON, is set aside with a warning and the inputs
    are hashed afresh (right digests either way)."""
    import splattwin.limits as limits

    f = tmp_path / "photo.jpg"
    f.write_bytes(b"x" * 1000)
    cache_path = tmp_path / ".splattwin" / "digests.json"
    cache_path.parent.mkdir()
    c = DigestCache(cache_path)
    assert c.file(f) == sha256_file(f)
    c.save()
    assert len(DigestCache(cache_path)._entries) == 1            # read back within the limit

    data = json.loads(cache_path.read_text())
    data["files"]["/padding"] = [[0, 0, 0, 0], "p" * 5000]      # a cache larger than the (lowered) limit
    cache_path.write_text(json.dumps(data))
    monkeypatch.setattr(limits, "MAX_RECORD_BYTES", 4096)
    with caplog.at_level(logging.WARNING, logger="splattwin.hashing"):
        big = DigestCache(cache_path)
    assert big._entries == {} and "hashing inputs afresh" in caplog.text and "limit" in caplog.text
    assert big.file(f) == sha256_file(f)

    cache_path.write_text("[" * 200000)                        # deep nesting: a warning, no RecursionError
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="splattwin.hashing"):
        assert DigestCache(cache_path)._entries == {}
    assert "hashing inputs afresh" in caplog.text
