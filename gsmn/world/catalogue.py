"""The landmark catalogue as data: the names, noun phrases and radius classes of the 63 landmark models, in class-id
order (paper: Environment; 45 unique noun phrases, see gsmn.world.landmarks).

World sampling, instructions and the model's heads need only these, so they read this module and import without the
mesh builder; gsmn.world.landmarks builds each entry's mesh (trimesh) and pairs it with the entry of the same name.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LandmarkClass:
    """A catalogue entry's identity: the perception head's class `CATALOGUE.index(entry)`."""

    name: str  # unique snake_case id, e.g. "fir_tree", "rock_2"
    noun_phrase: str  # lower-case words used in instructions, e.g. "fir tree", "rock"
    radius: float  # radius class in metres, 2.25 .. 3.75: the goal point lies this far from the centre


CATALOGUE: tuple[LandmarkClass, ...] = tuple(LandmarkClass(*row) for row in (
    ("fir_tree", "fir tree", 3.075),
    ("christmas_tree_1", "christmas tree", 3.125),
    ("christmas_tree_2", "christmas tree", 2.9),
    ("palm_tree_1", "palm tree", 3.35),
    ("palm_tree_2", "palm tree", 3.4),
    ("palm_tree_3", "palm tree", 3.475),
    ("palm_tree_4", "palm tree", 3.15),
    ("bush_1", "bush", 2.825),
    ("bush_2", "bush", 3.0),
    ("bush_3", "bush", 3.325),
    ("cactus", "cactus", 2.6),
    ("mushroom_1", "mushroom", 2.475),
    ("mushroom_2", "mushroom", 2.7),
    ("pumpkin", "pumpkin", 2.375),
    ("rock_1", "rock", 2.875),
    ("rock_2", "rock", 3.25),
    ("rock_3", "rock", 3.025),
    ("rock_4", "rock", 3.45),
    ("stone_circle", "stone circle", 3.575),
    ("house_1", "house", 3.7),
    ("house_2", "house", 3.75),
    ("house_3", "house", 3.6),
    ("wooden_house", "wooden house", 3.65),
    ("tower_1", "tower", 3.425),
    ("tower_2", "tower", 3.375),
    ("lighthouse", "lighthouse", 3.225),
    ("windmill", "windmill", 3.625),
    ("water_tower", "water tower", 3.525),
    ("igloo", "igloo", 3.175),
    ("tent", "tent", 3.275),
    ("phone_booth", "phone booth", 2.5),
    ("well_1", "well", 3.3),
    ("well_2", "well", 3.1),
    ("pyramid", "pyramid", 3.75),
    ("arch", "arch", 3.675),
    ("column", "column", 2.775),
    ("fountain", "fountain", 3.55),
    ("statue", "statue", 2.85),
    ("totem_pole", "totem pole", 2.8),
    ("barrel_1", "barrel", 2.425),
    ("barrel_2", "barrel", 2.45),
    ("barrel_3", "barrel", 2.675),
    ("red_barrel", "red barrel", 2.4),
    ("box_1", "box", 2.625),
    ("box_2", "box", 2.65),
    ("container", "container", 3.725),
    ("cone_1", "cone", 2.725),
    ("cone_2", "cone", 2.75),
    ("traffic_cone", "traffic cone", 2.25),
    ("tire_stack", "tire stack", 2.325),
    ("hay_bale", "hay bale", 2.975),
    ("anvil", "anvil", 2.35),
    ("globe", "globe", 2.55),
    ("snowman", "snowman", 2.525),
    ("gorilla", "gorilla", 2.95),
    ("stop_sign", "stop sign", 2.3),
    ("street_lamp", "street lamp", 2.575),
    ("mailbox", "mailbox", 2.275),
    ("bench", "bench", 2.925),
    ("satellite_dish", "satellite dish", 3.05),
    ("car", "car", 3.2),
    ("tank", "tank", 3.75),
    ("boat", "boat", 3.5),
))
NOUN_PHRASES: tuple[str, ...] = tuple(sorted({c.noun_phrase for c in CATALOGUE}))
