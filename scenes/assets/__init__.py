"""Procedural assets, no downloads: car, van, truck, bus, pedestrian, cyclist, motorcyclist,
traffic cone; plus street furniture and the city's static geometry, and user-supplied meshes.

- `catalog`: size distributions and the plain-data parameters of each family (numpy only).
- `vehicles`, `people`, `props`: the family builders, parameters -> parts (trimesh meshes).
- `static`: roads, sidewalks, markings, buildings and furniture as parts.
- `user`: a folder of glTF/OBJ files named by a small TOML.

Every agent mesh lives in the contract's object frame (x forward, y left, z up, origin at the
cuboid centre) and fills its cuboid: `build_agent_parts` fits the assembled design onto the
drawn dims exactly, and the design is made from those dims so that the fit is a small correction.
"""
