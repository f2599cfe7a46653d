"""Point-mass maze domain (docs/tasks.md §4.5 and §6, paper Appendix I).

The model is the stock planar point mass with the authors' maze edits applied programmatically
(docs/tasks.md §6): contacts enabled, a plus-shaped interior wall made of two boxes, and the target
sphere moved to the task's room and made non-colliding. The four tasks share the dynamics and the
initial-state distribution and differ only in the target position.
"""

from __future__ import annotations

from dm_control.rl import control
from dm_control.suite import base, common
from dm_control.suite import point_mass as stock_point_mass
from dm_control.suite.utils import randomizers
from lxml import etree

from dvfb.envs._common import as_random_state

TIME_LIMIT_S = 20  # 1000 steps of 0.02 s, 1 substep (docs/tasks.md §4.5)

TARGETS: dict[str, tuple[float, float]] = {
    "reach_top_left": (-0.15, 0.15),
    "reach_top_right": (0.15, 0.15),
    "reach_bottom_left": (-0.15, -0.15),
    "reach_bottom_right": (0.15, -0.15),
}
TARGET_HEIGHT = 0.01

# The start room (top left): x ~ U[-0.29, -0.15), y ~ U[0.15, 0.29) (docs/tasks.md §4.5).
START_X_RANGE = (-0.29, -0.15)
START_Y_RANGE = (0.15, 0.29)

# Interior walls (docs/tasks.md §6, item 4): name -> (half-sizes in the geom frame, local z axis).
# Both are centred at (0, 0, 0.02). maze_y spans x in [-0.18, 0.18], y in [-0.02, 0.02];
# maze_x spans x in [-0.02, 0.02], y in [-0.18, 0.18]; both z in [0, 0.04].
WALL_CENTRE = "0 0 0.02"
WALLS: dict[str, tuple[str, str]] = {
    "maze_y": ("0.18 0.02 0.02", "0 1 0"),
    "maze_x": ("0.02 0.18 0.02", "1 0 0"),
}


def maze_model_xml(target_xy: tuple[float, float]) -> bytes:
    """The stock point-mass MJCF with the maze edits of docs/tasks.md §6 and the target at ``target_xy``.

    Edits: (1) remove the ``contact="disable"`` flag; (3) add a default class ``wall`` (box geoms,
    stock material ``site``); (4) add the boxes ``maze_y`` and ``maze_x``, colliding with the
    default contype/conaffinity; (5) move the target sphere to ``target_xy`` at z = 0.01 and give it
    contype = conaffinity = 0. Edit (2), the authors' unused material ``self2``, is omitted because
    no geom refers to it.
    """
    root = etree.XML(common.read_model("point_mass.xml"), etree.XMLParser(remove_blank_text=True))

    for flag in root.findall("./option/flag"):
        if flag.get("contact") == "disable":
            del flag.attrib["contact"]
            if not flag.attrib:
                flag.getparent().remove(flag)

    default = root.find("./default")
    wall_class = etree.SubElement(default, "default", {"class": "wall"})
    etree.SubElement(wall_class, "geom", {"type": "box", "material": "site"})

    worldbody = root.find("./worldbody")
    for name, (half_sizes, z_axis) in WALLS.items():
        etree.SubElement(
            worldbody,
            "geom",
            {
                "name": name,
                "class": "wall",
                "pos": WALL_CENTRE,
                "size": half_sizes,
                "zaxis": z_axis,
            },
        )

    target = worldbody.find("./geom[@name='target']")
    target.set("pos", f"{target_xy[0]} {target_xy[1]} {TARGET_HEIGHT}")
    target.set("contype", "0")
    target.set("conaffinity", "0")
    return etree.tostring(root, pretty_print=True)


class MazeReach(stock_point_mass.PointMass):
    """Reach a target in the maze (docs/tasks.md §4.5).

    Reward: the stock point-mass reward, which is exactly the §4.5 formula:
    ``near * small_control`` with near = tol(dist; [0, 0.015], m=0.015, gaussian) and
    small_control = (mean_i(1 - u_i^2) + 4) / 5 on the raw applied control u
    (``physics.control()``, not clamped to the control range).

    Initial state: the stock randomiser runs first and makes its two task-RNG draws (kept so the
    task RNG stream matches the authors'), then the position is overwritten with a draw in the
    top-left room from ``start_random``. The authors draw that from the process-global NumPy RNG;
    here it is a seeded ``RandomState`` owned by the task (see :meth:`reseed`).
    """

    def __init__(self, random=None, start_random=None):
        super().__init__(randomize_gains=False, random=random)
        self.start_random = as_random_state(start_random)

    def reseed(self, seed: int) -> None:
        """Reseed both RNGs from ``seed``: the task RNG and the start-position RNG.

        Both become ``RandomState(seed)``. The start RNG thus replays the stream the authors' code
        draws from the global RNG right after ``np.random.seed(seed)``.
        """
        self.random.seed(seed)
        self.start_random.seed(seed)

    def initialize_episode(self, physics) -> None:
        # Stock randomiser: root_x, root_y ~ U[-0.29, 0.29] from the task RNG (two dummy draws).
        randomizers.randomize_limited_and_rotational_joints(physics, self.random)
        physics.named.data.qpos["root_x"] = self.start_random.uniform(*START_X_RANGE)
        physics.named.data.qpos["root_y"] = self.start_random.uniform(*START_Y_RANGE)
        # Skip PointMass.initialize_episode (it would randomise again); run the base-class hook.
        base.Task.initialize_episode(self, physics)


def make_task(task: str, seed: int | None = None) -> MazeReach:
    """The task object for ``point_mass_maze_<task>``; both of its RNGs are seeded with ``seed``."""
    if task not in TARGETS:
        raise KeyError(task)
    return MazeReach(random=seed, start_random=seed)


def build_environment(task: str, seed: int | None = None) -> control.Environment:
    """A dm_control environment for ``point_mass_maze_<task>``: maze model, 1 substep, 20 s."""
    task_object = make_task(task, seed)
    physics = stock_point_mass.Physics.from_xml_string(maze_model_xml(TARGETS[task]), common.ASSETS)
    return control.Environment(physics, task_object, time_limit=TIME_LIMIT_S)
