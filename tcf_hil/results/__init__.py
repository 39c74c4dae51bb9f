"""A finished run's results for people and their tools: the self-contained HTML report
(:mod:`.report`) and the exports to LAS/LAZ/PLY/PCD clouds and CSV/GeoJSON stems
(:mod:`.export`).

May import the world (the terrain's formula for the map), the devices' fault log, the
recordings and the evaluation; never a run (a run hands its directory and manifest over).
"""
