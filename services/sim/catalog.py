"""What a generated house is made of: room kinds, the furniture typical of each, small objects.

Everything here is data. Sizes are metres (width along the wall, depth away from it, height). Colours are
names from :data:`COLORS` (RGB 0..255) so that questions can ask about them in words.
"""

from __future__ import annotations

from dataclasses import dataclass

ROOM_KINDS: tuple[str, ...] = (
    "kitchen",
    "bedroom",
    "bathroom",
    "living_room",
    "dining_room",
    "hallway",
    "office",
    "laundry",
    "garage",
    "storage",
)

COLORS: dict[str, tuple[int, int, int]] = {
    "red": (200, 40, 40),
    "green": (50, 160, 60),
    "blue": (40, 80, 200),
    "yellow": (230, 200, 40),
    "orange": (235, 130, 30),
    "purple": (130, 60, 170),
    "pink": (235, 130, 180),
    "white": (235, 235, 235),
    "black": (30, 30, 30),
    "gray": (130, 130, 130),
    "brown": (120, 75, 40),
    "beige": (210, 190, 150),
}

# Surfaces of each room kind: floor colour and wall colour.
ROOM_FINISH: dict[str, tuple[tuple[int, int, int], tuple[int, int, int]]] = {
    "kitchen": ((190, 180, 160), (225, 222, 205)),
    "bedroom": ((150, 110, 80), (205, 215, 225)),
    "bathroom": ((200, 205, 210), (200, 225, 230)),
    "living_room": ((140, 100, 70), (230, 220, 200)),
    "dining_room": ((160, 115, 80), (225, 210, 190)),
    "hallway": ((170, 150, 120), (215, 215, 210)),
    "office": ((120, 110, 100), (210, 220, 205)),
    "laundry": ((185, 185, 185), (220, 230, 235)),
    "garage": ((110, 110, 110), (180, 180, 175)),
    "storage": ((130, 120, 110), (195, 190, 180)),
}
CEILING_RGB = (245, 245, 240)


@dataclass(frozen=True)
class FurnitureKind:
    """A piece of furniture: a box (``shape="box"``), a table on legs (``"table"``), a seat with a back
    (``"seat"``) or open shelves (``"shelf"``). ``surface`` = small objects can stand on top of it."""

    category: str
    size: tuple[float, float, float]
    colors: tuple[str, ...]
    shape: str = "box"
    surface: bool = True
    against_wall: bool = True


@dataclass(frozen=True)
class SmallObjectKind:
    """A small object. ``states`` is the set of visible states it can be in (empty = none); ``on`` lists the
    furniture categories it stands on (``"floor"`` = on the floor next to a piece of furniture)."""

    category: str
    size: tuple[float, float, float]
    colors: tuple[str, ...]
    states: tuple[str, ...] = ()
    on: tuple[str, ...] = ()
    rooms: tuple[str, ...] = ()


def _f(category: str, size: tuple[float, float, float], colors: tuple[str, ...], **kw: object) -> FurnitureKind:
    return FurnitureKind(category, size, colors, **kw)  # type: ignore[arg-type]


FURNITURE: dict[str, FurnitureKind] = {
    f.category: f
    for f in (
        _f("bed", (1.6, 2.0, 0.55), ("white", "gray", "blue", "beige")),
        _f("nightstand", (0.5, 0.45, 0.55), ("brown", "white", "black")),
        _f("wardrobe", (1.2, 0.6, 2.0), ("brown", "white"), surface=False),
        _f("dresser", (1.2, 0.5, 0.85), ("brown", "white", "black")),
        _f("sofa", (2.0, 0.9, 0.85), ("gray", "blue", "green", "beige", "brown"), shape="seat"),
        _f("armchair", (0.9, 0.85, 0.9), ("gray", "red", "beige"), shape="seat"),
        _f("coffee_table", (1.1, 0.6, 0.45), ("brown", "black", "white"), shape="table", against_wall=False),
        _f("tv_stand", (1.6, 0.45, 0.5), ("black", "brown", "white")),
        _f("bookshelf", (1.0, 0.35, 1.8), ("brown", "white", "black"), shape="shelf"),
        _f("dining_table", (1.6, 0.9, 0.75), ("brown", "white", "black"), shape="table", against_wall=False),
        _f("chair", (0.45, 0.45, 0.9), ("brown", "black", "white"), shape="seat", surface=False),
        _f("sideboard", (1.6, 0.45, 0.85), ("brown", "white")),
        _f("kitchen_counter", (2.4, 0.6, 0.9), ("white", "gray", "beige")),
        _f("refrigerator", (0.8, 0.7, 1.8), ("white", "gray", "black"), surface=False),
        _f("stove", (0.6, 0.6, 0.9), ("white", "black", "gray")),
        _f("kitchen_island", (1.6, 0.9, 0.9), ("white", "brown", "gray"), against_wall=False),
        _f("toilet", (0.4, 0.65, 0.75), ("white",), surface=False),
        _f("bathroom_sink", (0.8, 0.5, 0.85), ("white", "beige")),
        _f("bathtub", (1.7, 0.75, 0.55), ("white",), surface=False),
        _f("shower", (0.9, 0.9, 2.0), ("white", "gray"), surface=False),
        _f("desk", (1.4, 0.7, 0.75), ("brown", "white", "black"), shape="table"),
        _f("office_chair", (0.6, 0.6, 1.0), ("black", "gray", "blue"), shape="seat", surface=False),
        _f("filing_cabinet", (0.5, 0.6, 1.1), ("gray", "black", "white")),
        _f("washing_machine", (0.6, 0.6, 0.85), ("white", "gray")),
        _f("dryer", (0.6, 0.6, 0.85), ("white", "gray")),
        _f("laundry_shelf", (1.2, 0.4, 1.8), ("white", "gray"), shape="shelf"),
        _f("car", (1.8, 4.2, 1.45), ("red", "blue", "black", "white", "gray"), against_wall=False, surface=False),
        _f("workbench", (2.0, 0.7, 0.9), ("brown", "gray")),
        _f("storage_shelf", (1.5, 0.5, 1.9), ("gray", "brown"), shape="shelf"),
        _f("bench", (1.2, 0.4, 0.45), ("brown", "white", "black")),
        _f("coat_rack", (0.5, 0.4, 1.8), ("black", "brown"), surface=False),
        _f("console_table", (1.0, 0.35, 0.8), ("brown", "black", "white"), shape="table"),
        _f("side_table", (0.5, 0.5, 0.55), ("brown", "white", "black"), shape="table"),
        _f("cabinet", (1.0, 0.5, 0.9), ("white", "brown", "gray")),
    )
}

# Furniture typical of each room kind, in the order it is placed (first = most important). A generated room
# draws its pieces from this list (the first two always, the rest while space remains).
ROOM_FURNITURE: dict[str, tuple[str, ...]] = {
    "kitchen": ("kitchen_counter", "refrigerator", "stove", "kitchen_island", "cabinet", "chair"),
    "bedroom": ("bed", "nightstand", "wardrobe", "dresser", "nightstand", "chair", "bookshelf"),
    "bathroom": ("toilet", "bathroom_sink", "bathtub", "shower", "cabinet"),
    "living_room": ("sofa", "tv_stand", "coffee_table", "armchair", "bookshelf", "side_table", "armchair"),
    "dining_room": ("dining_table", "sideboard", "chair", "chair", "cabinet", "chair"),
    "hallway": ("console_table", "coat_rack", "bench", "cabinet"),
    "office": ("desk", "office_chair", "bookshelf", "filing_cabinet", "side_table"),
    "laundry": ("washing_machine", "dryer", "laundry_shelf", "cabinet"),
    "garage": ("car", "workbench", "storage_shelf", "storage_shelf"),
    "storage": ("storage_shelf", "storage_shelf", "cabinet", "storage_shelf"),
}

SMALL_OBJECTS: dict[str, SmallObjectKind] = {
    o.category: o
    for o in (
        SmallObjectKind("lamp", (0.3, 0.3, 0.5), ("white", "black", "beige", "gray"), ("on", "off"),
                        ("nightstand", "side_table", "desk", "dresser", "console_table")),
        SmallObjectKind("laptop", (0.34, 0.24, 0.03), ("gray", "black", "white"), ("open", "closed"),
                        ("desk", "coffee_table", "dining_table", "bed", "kitchen_island")),
        SmallObjectKind("television", (1.1, 0.08, 0.65), ("black",), ("on", "off"), ("tv_stand",)),
        SmallObjectKind("towel", (0.5, 0.3, 0.08), ("white", "blue", "pink", "yellow", "gray"),
                        ("folded", "unfolded"), ("bathroom_sink", "cabinet", "laundry_shelf", "dryer", "bed")),
        SmallObjectKind("blanket", (0.7, 0.5, 0.1), ("red", "blue", "gray", "beige", "green"),
                        ("folded", "unfolded"), ("bed", "sofa", "armchair", "bench")),
        SmallObjectKind("box", (0.4, 0.3, 0.3), ("brown", "white"), ("open", "closed"),
                        ("storage_shelf", "floor", "workbench", "cabinet", "laundry_shelf")),
        SmallObjectKind("suitcase", (0.45, 0.25, 0.65), ("black", "red", "blue", "gray", "green"), (),
                        ("floor",), ("bedroom", "hallway", "storage", "garage", "living_room")),
        SmallObjectKind("backpack", (0.3, 0.2, 0.45), ("black", "red", "blue", "green", "orange"), (),
                        ("floor", "bench")),
        SmallObjectKind("vase", (0.18, 0.18, 0.35), ("white", "blue", "green", "red", "yellow"), (),
                        ("dining_table", "sideboard", "console_table", "coffee_table", "side_table")),
        SmallObjectKind("potted_plant", (0.35, 0.35, 0.7), ("green",), (), ("floor",)),
        SmallObjectKind("book", (0.22, 0.16, 0.04), ("red", "blue", "green", "yellow", "black"), (),
                        ("bookshelf", "desk", "nightstand", "coffee_table")),
        SmallObjectKind("mug", (0.1, 0.1, 0.11), ("white", "red", "blue", "black", "yellow"), (),
                        ("kitchen_counter", "desk", "dining_table", "kitchen_island", "coffee_table")),
        SmallObjectKind("kettle", (0.22, 0.18, 0.25), ("white", "black", "red", "gray"), ("on", "off"),
                        ("kitchen_counter", "kitchen_island")),
        SmallObjectKind("microwave", (0.5, 0.38, 0.3), ("white", "black", "gray"), ("open", "closed"),
                        ("kitchen_counter",)),
        SmallObjectKind("fruit_bowl", (0.3, 0.3, 0.12), ("white", "blue", "brown"), (),
                        ("kitchen_island", "dining_table", "kitchen_counter")),
        SmallObjectKind("laundry_basket", (0.5, 0.35, 0.4), ("white", "blue", "gray", "brown"), (),
                        ("floor",), ("laundry", "bedroom", "bathroom")),
        SmallObjectKind("trash_can", (0.3, 0.3, 0.45), ("gray", "black", "white"), ("open", "closed"),
                        ("floor",)),
        SmallObjectKind("shoes", (0.3, 0.25, 0.12), ("black", "white", "brown", "red"), (),
                        ("floor",), ("hallway", "bedroom", "garage")),
        SmallObjectKind("toolbox", (0.45, 0.22, 0.22), ("red", "yellow", "black", "blue"), ("open", "closed"),
                        ("workbench", "storage_shelf", "floor"), ("garage", "storage")),
        SmallObjectKind("monitor", (0.6, 0.18, 0.4), ("black", "white"), ("on", "off"), ("desk",)),
        SmallObjectKind("cushion", (0.4, 0.4, 0.15), ("red", "blue", "yellow", "green", "orange", "beige"), (),
                        ("bed", "bench", "sofa", "armchair")),
        SmallObjectKind("umbrella", (0.12, 0.12, 0.9), ("black", "red", "blue", "yellow"), ("open", "closed"),
                        ("floor",), ("hallway", "garage")),
    )
}

# Words of states in questions: the opposite of each state.
OPPOSITE_STATE: dict[str, str] = {
    "on": "off",
    "off": "on",
    "open": "closed",
    "closed": "open",
    "folded": "unfolded",
    "unfolded": "folded",
}

STRUCTURE_CATEGORIES: frozenset[str] = frozenset({"floor", "wall", "ceiling", "door_frame"})


@dataclass
class HouseLimits:
    """Bounds of the generator (the issue's numbers)."""

    min_area_m2: float = 100.0
    max_area_m2: float = 800.0
    min_rooms: int = 4
    max_rooms: int = 14
    wall_height: float = 2.7
    wall_thickness: float = 0.1
    door_width: float = 1.0
    door_height: float = 2.1


def display_name(name: str) -> str:
    """Human-readable name of a room kind or category: ``display_name("living_room") == "living room"``."""
    return name.replace("_", " ")


# Categories whose name is already plural ("the shoes are", not "the shoes is").
PLURAL_ONLY: frozenset[str] = frozenset({"shoes"})


def plural(name: str) -> str:
    """English plural of a category's display name (``"box"`` -> ``"boxes"``)."""
    word = display_name(name)
    if name in PLURAL_ONLY:
        return word
    if word.endswith(("s", "x", "sh", "ch")):
        return word + "es"
    return word + "s"
