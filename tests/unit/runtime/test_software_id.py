"""What a batch task's key knows of the software: ``runtime.batch.tree_digest`` and
``software_id``."""

from __future__ import annotations

import re
from pathlib import Path

from groundstation.runtime.batch import software_id, tree_digest


def _tree(root: Path) -> Path:
    (root / "pkg" / "sub").mkdir(parents=True)
    (root / "pkg" / "a.py").write_text("x = 1\n")
    (root / "pkg" / "sub" / "model.json").write_text('{"w": [0.5]}')
    return root / "pkg"


def test_the_digest_follows_every_files_bytes_and_name_not_compiled_caches(tmp_path):
    pkg = _tree(tmp_path)
    base = tree_digest(pkg)
    assert tree_digest(pkg) == base and len(base) == 64
    (pkg / "__pycache__").mkdir()
    (pkg / "__pycache__" / "a.cpython-311.pyc").write_bytes(b"\x00\x01")
    assert tree_digest(pkg) == base  # caches follow the sources
    (pkg / "sub" / "model.json").write_text('{"w": [0.6]}')
    changed = tree_digest(pkg)
    assert changed != base  # a data file the code reads is code too
    (pkg / "sub" / "model.json").rename(pkg / "sub" / "other.json")
    assert tree_digest(pkg) not in (base, changed)  # same bytes under another name
    (pkg / "sub" / "other.json").rename(pkg / "sub" / "model.json")
    assert tree_digest(pkg) == changed


def test_the_software_id_is_the_version_and_the_packages_digest():
    sid = software_id()
    assert re.fullmatch(r"[^+]+\+[0-9a-f]{12}", sid)
    import groundstation

    assert sid.endswith("+" + tree_digest(Path(groundstation.__file__).parent)[:12])
