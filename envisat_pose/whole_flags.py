"""The one argparse parser of the repository's command lines (the `envisat` verbs, the benches, the scripts): it
takes each flag only as spelled whole, so a typo or a shortened flag is argparse's one line of usage error instead
of silently meaning another flag (`--seed` for `--seeds`, `--dur` for `--duration-s`). Standard library only."""

from __future__ import annotations

import argparse


class WholeFlagParser(argparse.ArgumentParser):
    """argparse's parser that takes each flag only as spelled whole (allow_abbrev=False): `--duration` is refused,
    not read as `--duration-s`, and a flag added later cannot change what an abbreviation meant. Its subparsers
    (add_subparsers' parser_class: the parser's own class) are of this class too, so every verb refuses them."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
