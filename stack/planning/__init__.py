"""Grid path planning: Fan et al. 2021, improved Q-learning (the offline part, issue 8).

* :mod:`.grid` -- ASCII maps (``maps/`` at the repository root), the 8-action grid world, the 3 x 3
  sensor and the virtual obstacle filling test (section 3.2);
* :mod:`.qlearning` -- Q-L1..Q-L5 of Table 1; :func:`plan` takes any boolean occupancy ``[x, y]``
  with start and goal cells, and warm-starts from a previous result for cheap replanning;
* :mod:`.tracking` -- follower tracking (section 4.1) and the triangle formation (section 5.2);
* :mod:`.runner` -- plans beside the control step (a worker thread; the step adopts a finished plan);
* :mod:`.plots` -- Fig. 5-8 (imports matplotlib; not imported here).

Imports numpy, matplotlib (plots only) and the standard library: nothing else of the stack.
"""

from .grid import ACTIONS, MAPS_DIR, GridMap, GridWorld, MapError, find_map, load_map, parse_map, path_length
from .qlearning import VARIANTS, QLearningConfig, QLearningResult, plan, plan_map
from .tracking import FormationResult, TrackingConfig, formation_experiment, run_formation

__all__ = ["ACTIONS", "MAPS_DIR", "GridMap", "GridWorld", "MapError", "find_map", "load_map", "parse_map",
           "path_length", "VARIANTS", "QLearningConfig", "QLearningResult", "plan", "plan_map",
           "FormationResult", "TrackingConfig", "formation_experiment", "run_formation"]
