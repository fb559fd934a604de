"""docs/reference.md's layout names every module of the package, in the row of its room."""

import re
from pathlib import Path

import pytest

import uavsearch

PKG = Path(uavsearch.__file__).resolve().parent
REFERENCE = PKG.parent / "docs" / "reference.md"


def _layout_rows() -> dict[str, str]:
    """{room cell: modules cell} of the layout's room table."""
    text = REFERENCE.read_text()
    section = text[text.index("## Layout"):text.index("## Conventions")]
    table = section[section.index("| room |"):].split("\n\n")[0]  # the first table: rooms and modules
    rows = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        rows[cells[0]] = cells[1]
    return rows


def _room_of(rel: Path) -> str:
    """The layout row a module belongs in: its sub-folder of search/, else its top-level folder."""
    parts = rel.parts
    if parts[0] == "search" and len(parts) > 2:
        return f"`search/{parts[1]}/`"
    return f"`{parts[0]}/`" if len(parts) > 1 else ""


def test_layout_names_every_module_in_its_room():
    rows = _layout_rows()
    missing = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG)
        if rel.name == "__init__.py" and len(rel.parts) > 1:
            continue  # a room's __init__ is the room itself
        room = _room_of(rel)
        if room:
            cell = rows.get(room, "")
            depth = room.strip("`").count("/")  # search/train/ -> 2 folders, world/ -> 1
            inner = Path(*rel.parts[depth:])
            if f"`{inner.as_posix()}`" not in cell and f"`{rel.as_posix()}`" not in cell:
                missing.append(f"{rel} (row {room})")
        elif not any(f"`{rel.as_posix()}`" in cell or f"`{rel.as_posix()}`" in key for key, cell in rows.items()):
            missing.append(str(rel))
    assert not missing, "docs/reference.md's layout does not name: " + ", ".join(missing)


def test_layout_rows_name_only_modules_that_exist():
    rows = _layout_rows()
    stale = []
    for room, cell in rows.items():
        base = PKG / room.strip("`") if room.startswith("`") and room.endswith("/`") else PKG
        for name in re.findall(r"`([\w/]+\.py)`", cell):
            if not (base / name).is_file() and not (PKG / name).is_file():
                stale.append(f"{name} (row {room})")
    assert not stale, "docs/reference.md's layout names modules that do not exist: " + ", ".join(stale)


def _path_rows() -> dict[str, str]:
    """{path: what} of the layout's second table: the repository's folders beside the package."""
    text = REFERENCE.read_text()
    section = text[text.index("## Layout"):text.index("## Conventions")]
    table = section[section.index("| path |"):].split("\n\n")[0]
    rows = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        rows[cells[0].strip("`")] = cells[1]
    return rows


def test_layout_paths_exist():
    missing = [p for p in _path_rows() if not (PKG.parent / p).exists()]
    assert not missing, "docs/reference.md's layout names paths that do not exist: " + ", ".join(missing)


@pytest.mark.parametrize("folder", ["tools/", "examples/"])
def test_layout_names_every_script_and_only_those(folder):
    """The scripts users run are listed one by one, so a new or a removed one shows here."""
    cell = _path_rows()[folder]
    on_disk = {p.name for p in (PKG.parent / folder).iterdir() if p.suffix in (".py", ".sh")}
    named = set(re.findall(r"`([\w.-]+\.(?:py|sh))`", cell))
    row = f"docs/reference.md's `{folder}` row"
    assert not on_disk - named, f"{row} does not name: " + ", ".join(sorted(on_disk - named))
    assert not named - on_disk, f"{row} names files that do not exist: " + ", ".join(sorted(named - on_disk))
