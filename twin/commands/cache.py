"""`vrscroll cache`: what the cache folder holds ($VRSCROLL_CACHE, default ~/.cache/vrscroll), and clearing it.

`show` (the default) lists each kind of cached file (fields: a target's SDF grids; firmware: the C core's
builds; ...) with its count and size, and the fields' cap (twin.morphpatch.fields.CACHE_CAP: the least
recently used go first beyond it). `clear` removes the cached files of one kind (`--kind`) or of all; each is
built again when next needed.
"""

from __future__ import annotations

from twin.errors import UserError
from twin.morphpatch.fields import CACHE_CAP, cache_files
from twin.paths import cache_dir


def add_arguments(p) -> None:
    p.add_argument("action", nargs="?", choices=("show", "clear"), default="show",
                   help="show what the cache holds (default), or clear it")
    p.add_argument("--kind", metavar="KIND", help="only this kind of cached file (a folder `show` lists, e.g. fields)")


def _size(n: int) -> str:
    """A byte count for people: B, kB, MB, GB (powers of 1000)."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def run(args) -> int:
    root = cache_dir("")
    kinds = sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    if args.kind is not None:
        if "/" in args.kind or args.kind in ("", ".", ".."):
            raise UserError(f"--kind {args.kind!r}: a kind is one folder name of the cache (e.g. fields)")
        if args.kind not in kinds:
            raise UserError(f"--kind {args.kind}: the cache {root} holds no such kind"
                            + (f" (it holds {', '.join(kinds)})" if kinds else " (it is empty)"))
        kinds = [args.kind]
    if args.action == "clear":
        removed = total = 0
        for kind in kinds:
            for path in cache_files(root / kind):
                total += path.stat().st_size
                path.unlink(missing_ok=True)
                removed += 1
        print(f"cleared {removed} file(s), {_size(total)}, from {root}" + (f" ({args.kind})" if args.kind else ""))
        return 0
    print(f"cache {root}" + ("" if kinds else ": empty"))
    for kind in kinds:
        files = cache_files(root / kind)
        size = sum(p.stat().st_size for p in files)
        cap = f" of at most {_size(CACHE_CAP)}" if kind == "fields" else ""
        print(f"  {kind}: {len(files)} file(s), {_size(size)}{cap}")
    return 0
