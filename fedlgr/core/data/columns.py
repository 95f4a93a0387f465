"""The MANNERS-DB column layout (docs/data.md), written exactly as the dataset spells it.

``all_data.csv`` has one row per *rating*: the scene id, the two mode flags, 27 scene
descriptors normalised to 0..1 and the 8 Likert labels (1..5). The names below are the
dataset's own, typos included (``3d closest human facing robot?``).
"""

CSV_NAME = "all_data.csv"  # the ratings file of a dataset folder
STAMP = "Stamp"
USING_CIRCLE = "Using circle"
USING_ARROW = "Using arrow"
MODE_COLUMNS: tuple[str, ...] = (USING_CIRCLE, USING_ARROW)

DESCRIPTOR_COLUMNS: tuple[str, ...] = (
    "Number of people",
    "Number of people in group",
    "Group radius",
    "Distance to group",
    "Robot within group?",
    "Robot facing group?",
    "Robot work radius",
    "Distance to closest human",
    "Distance to 2nd closest human",
    "Distance to 3rd closest human",
    "Direction to closest human",
    "Direction to 2nd closest human",
    "Direction to 3rd closest human",
    "Direction from closest human to robot",
    "Robot facing closest human?",
    "Robot facing 2nd closest human?",
    "Robot facing 3rd closest human?",
    "Closest human facing robot?",
    "2nd closest human facing robot?",
    "3d closest human facing robot?",
    "Number of children",
    "Distance to closest child",
    "Number of animals",
    "Distance to closest animal",
    "Number of people sitting/laying in sofa?",
    "Music playing?",
    "Number of agents in scene",
)

LABEL_COLUMNS: tuple[str, ...] = (
    "Vacuum cleaning",
    "Mopping the floor",
    "Carry warm food",
    "Carry cold food",
    "Carry drinks",
    "Carry small objects (plates, toys)",
    "Carry big objects (tables, chairs)",
    "Cleaning (Picking up stuff) / Starting conversation",
)

#: Short names for tables, plots and metric keys, in the order of ``LABEL_COLUMNS``.
LABEL_SHORT_NAMES: tuple[str, ...] = (
    "vacuum",
    "mop",
    "warm_food",
    "cold_food",
    "drinks",
    "small_objects",
    "big_objects",
    "conversation",
)

ALL_COLUMNS: tuple[str, ...] = (STAMP, *MODE_COLUMNS, *DESCRIPTOR_COLUMNS, *LABEL_COLUMNS)

#: The features modality: 27 descriptors followed by the 2 mode flags.
FEATURE_COLUMNS: tuple[str, ...] = (*DESCRIPTOR_COLUMNS, *MODE_COLUMNS)

LIKERT_MIN, LIKERT_MAX = 1, 5

assert len(DESCRIPTOR_COLUMNS) == 27 and len(LABEL_COLUMNS) == 8 and len(ALL_COLUMNS) == 38
