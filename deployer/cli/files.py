"""validate, docs and explain: commands about the files and their schemas."""

from __future__ import annotations

import os

import click

from ..errors import EXIT_INVALID, EXIT_OK, InputError, UsageError
from ..load.messages import clip
from .base import echo, safe


def validate_file(path: str) -> str:
    """Check one file of any kind; returns a one-line summary or raises InputError (``deployer.validate_file``)."""
    from ..api.commands import validate_file as check

    return check(path)


@click.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
def validate(files: tuple[str, ...]) -> int:
    """Check profiles, recipes and inventories (and saved plans and reports); exit 1 if any is invalid."""
    bad = 0
    for f in files:
        try:
            echo(f"{safe(f)}: ok ({safe(validate_file(f))})")
        except InputError as e:
            bad += 1
            for d in e.diagnostics:
                echo(safe(d), err=True)
    if bad:
        echo(f"{bad} of {len(files)} file{'s' if len(files) != 1 else ''} invalid", err=True)
        return EXIT_INVALID
    return EXIT_OK


@click.command("docs")
@click.option(
    "--out",
    "out_dir",
    default=os.path.join("docs", "reference"),
    show_default=True,
    type=click.Path(file_okay=False),
    help="where the reference pages go",
)
@click.option("--check", is_flag=True, help="write nothing; exit 1 when a page differs from the schemas")
@click.option("--force", is_flag=True, help="overwrite files of the pages' names that are not generated pages")
def docs_command(out_dir: str, check: bool, force: bool) -> int:
    """Generate the reference pages (one per file kind) from the JSON Schemas."""
    from .docgen import stale_pages, write_pages

    if check:
        stale = stale_pages(out_dir)
        for path in stale:
            echo(f"{safe(path)}: stale (run: deployer docs --out {safe(out_dir)})", err=True)
        return EXIT_INVALID if stale else EXIT_OK
    try:
        changed = write_pages(out_dir, force=force)
    except OSError as e:
        raise UsageError(f"cannot write the pages into {clip(out_dir, 300)}: {e.strerror or e}") from None
    echo(f"{len(changed)} page{'s' if len(changed) != 1 else ''} updated in {safe(out_dir)}", err=True)
    return EXIT_OK


# words of manuals and other tools -> (our key, what it is called here)
_TERMS = {
    "resolution": ("scale", "a parameter's resolution (a manual's '0.01 s units') is its scale"),
    "multiplier": ("scale", "a multiplier is a parameter's scale"),
    "factor": ("scale", "a scaling factor is a parameter's scale"),
    "gain": ("scale", "a register's gain (multiplier) is its scale"),
    "slave": ("recipe:device.unit", "a slave address is the unit id, device.unit (or --unit)"),
    "slave_id": ("recipe:device.unit", "a slave address is the unit id, device.unit (or --unit)"),
    "endianness": ("byte_order", "the byte and word order of multi-register values is byte_order"),
    "word_swap": ("byte_order", "a word swap is byte_order: CDAB (or swap: word)"),
}


@click.command()
@click.argument("key")
def explain(key: str) -> int:
    """Explain a key of a profile, recipe, inventory, plan or report, or a device URL option
    (e.g. max_frame_bytes, profile:scale, baudrate)."""
    import difflib

    from .docgen import all_keys, find_keys, render_text, url_option_text

    texts = [render_text(k) for k in find_keys(key)]
    kind, _, name = key.rpartition(":")
    if kind in ("", "url"):
        texts += [t for t in [url_option_text(name)] if t]
    if not texts and name.strip().lower() in _TERMS:  # a manual's word for what a key is called here
        ours = _TERMS[name.strip().lower()]
        texts = [f"'{name}' is not a key here: {ours[1]}.", *(render_text(k) for k in find_keys(ours[0]))]
    if not texts:
        names = sorted({k.path for k in all_keys()} | {k.path.rsplit(".", 1)[-1] for k in all_keys()})
        hint = difflib.get_close_matches(name, names, n=3) if len(name) <= 100 else []
        raise UsageError(
            f"no key '{clip(key)}' in any schema"
            + (f"; did you mean {', '.join(hint)}?" if hint else "; try e.g. 'deployer explain scale'")
        )
    echo("\n\n".join(texts))
    return EXIT_OK
