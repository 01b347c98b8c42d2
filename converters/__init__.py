"""Converters: public datasets into UrbanOmniView source datasets.

Each converter module exposes `add_arguments(parser)` and `run(args) -> int` and is listed in
CONVERTERS; `omnigen convert NAME` finds it here, so adding a dataset touches no CLI code.
"""

CONVERTERS: dict[str, str] = {
    "kitti": "omnigen.converters.kitti",
    "dair": "omnigen.converters.dair",
}
