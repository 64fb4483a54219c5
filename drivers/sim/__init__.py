"""The simulated rig: a ray-traced camera view of a projector-camera rig with a mirror, behind the same
driver interfaces as the hardware (drivers/base.py). See docs/SIMULATOR.md."""

from drivers.sim.render import Renderer, RenderSettings, SceneState, PlacedBoard
from drivers.sim.rig import SimCamera, SimOperator, SimProjector, SimRig, open_sim_rig
from drivers.sim.scenarios import DEFAULT_SCENARIO, Scenario, get_scenario, list_scenarios

__all__ = ["DEFAULT_SCENARIO", "PlacedBoard", "Renderer", "RenderSettings", "Scenario", "SceneState", "SimCamera",
           "SimOperator", "SimProjector", "SimRig", "get_scenario", "list_scenarios", "open_sim_rig"]
