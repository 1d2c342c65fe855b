"""The results index, ``experiments/results/index.json``: which folder backs which claim, and which are superseded.

The index is data, kept by hand beside the folders it describes::

    {"schema": 1,
     "statuses": {status: what it means},
     "record_schemas": {version: what a folder's race records look like},
     "folders": {name: {"status": "current" | "exploratory" | "superseded", "claim": what the folder shows,
                        "command": the command that made it as its README records it (null where none is recorded),
                        "record_schema": the version of its race records (null: it holds none),
                        "superseded_by": the folder that answers its claim now, "commit": the commit that holds it
                        (superseded folders only), "ships": a package file built from it (optional)}},
     "readme": [{"kind": how the row reads its folder, "folder": the folder's path in the checkout,
                 "claim": the row's claim, a template its kind fills, ...what its kind reads besides}]}

A folder the index marks current backs a claim of the README or the package's data; an exploratory one holds a probe,
a search or an earlier run the notes in ``docs/`` cite; a superseded one is gone from ``experiments/results/`` and
lives in the git history at its commit. :func:`load` refuses an index that disagrees with the folders beside it.
``pixelmpc report --readme`` writes the README's table from the ``readme`` rows
(:mod:`~experiments.reporting.readme_table`) and the list of folders in ``docs/results.md`` from the ``folders``
(:func:`folder_list`).
"""

from __future__ import annotations

import json
from pathlib import Path

from experiments.reporting import splice

RESULTS = Path("experiments/results")
INDEX = RESULTS / "index.json"
SCHEMA = 1
STATUSES = ("current", "exploratory", "superseded")
RESULTS_DOC = Path("docs/results.md")
BEGIN = "<!-- folders:begin -->"
END = "<!-- folders:end -->"


def load(root: Path) -> dict:
    """The index of the checkout ``root``, checked against the folders beside it (:func:`problems`): a ValueError
    names the first disagreement."""
    path = Path(root) / INDEX
    if not path.is_file():
        raise ValueError(f"{INDEX} not found under {root}")
    data = json.loads(path.read_text())
    found = problems(Path(root), data)
    if found:
        raise ValueError(f"{INDEX}: {found[0]}" + (f" (and {len(found) - 1} more)" if len(found) > 1 else ""))
    return data


def problems(root: Path, data: dict) -> list[str]:
    """Where the index ``data`` disagrees with the folders of ``root``'s ``experiments/results/``: its schema, a status
    it does not know, a superseded folder without its successor or commit or still on disk, a kept folder missing or
    without a README, a folder or file on disk it does not list, a README row on a folder it does not mark current."""
    if data.get("schema") != SCHEMA:
        return [f"schema {data.get('schema')!r}, this checkout reads schema {SCHEMA}"]
    folders, found = data["folders"], []
    for name, entry in sorted(folders.items()):
        status = entry.get("status")
        if status not in STATUSES:
            found.append(f"{name}: status {status!r}, not one of {', '.join(STATUSES)}")
        elif not entry.get("claim"):
            found.append(f"{name}: no claim")
        elif status == "superseded":
            successor = folders.get(entry.get("superseded_by"), {})
            if successor.get("status") not in ("current", "exploratory") or not entry.get("commit"):
                found.append(f"{name}: superseded, it must name a kept folder that superseded it and the commit that "
                             "holds it")
            if (root / RESULTS / name).exists():
                found.append(f"{name}: superseded, yet still in {RESULTS}")
        elif not (root / RESULTS / name / "README.md").is_file():
            found.append(f"{name}: {status}, yet {RESULTS / name / 'README.md'} is missing")
    on_disk = sorted(path.name for path in (root / RESULTS).iterdir() if path.name != INDEX.name)
    found += [f"{name}: in {RESULTS}, not in the index" for name in on_disk if name not in folders]
    for row in data.get("readme", []):
        folder = Path(row["folder"])
        if folder.parent == RESULTS and folders.get(folder.name, {}).get("status") != "current":
            found.append(f"the README row {row['kind']!r} reads {folder}, which the index does not mark current")
    return found


def folder_list(data: dict) -> str:
    """The folders of the index in Markdown, by status: each kept one linked with its claim, each superseded one with
    what superseded it and the commit that holds it."""
    lines = []
    for status in STATUSES:
        names = sorted(name for name, entry in data["folders"].items() if entry["status"] == status)
        lines += ["", f"**{status.capitalize()}** ({data['statuses'][status]}):", ""]
        for name in names:
            entry = data["folders"][name]
            if status == "superseded":
                lines.append(f"- `{name}/` (at {entry['commit']}): {entry['claim']}; superseded by "
                             f"[{entry['superseded_by']}](../{RESULTS.as_posix()}/{entry['superseded_by']}/README.md)")
            else:
                lines.append(f"- [{name}](../{RESULTS.as_posix()}/{name}/README.md): {entry['claim']}")
    return "\n".join(lines[1:])


def rewrite_results_doc(root: Path, check: bool = False) -> tuple[str, str]:
    """(``docs/results.md`` as it is, with its list of folders made from the index); the file is rewritten unless
    ``check`` (or it is current)."""
    path = Path(root) / RESULTS_DOC
    old = path.read_text()
    splice.check_markers(old, BEGIN, END, RESULTS_DOC.as_posix())
    new = splice.replace_block(old, folder_list(load(root)), BEGIN, END)
    if new != old and not check:
        path.write_text(new)
    return old, new
