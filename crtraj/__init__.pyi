"""The names `crtraj` loads on first use (``__init__.py``, PEP 562), seen statically: by type checkers, IDEs
and the API reference (griffe). tests/test_public_api.py keeps it equal to ``crtraj.__all__``."""

from crtraj.app.devices._stream import admit_result as admit_result
from crtraj.app.lab._calibrate_file import Calibration as Calibration
from crtraj.app.lab._calibrate_file import calibrate_robot as calibrate_robot
from crtraj.app.lab._record import excitation_motion as excitation_motion
from crtraj.app.lab._record import record_dataset as record_dataset
from crtraj.app.lab._verify import Verification as Verification
from crtraj.app.lab._verify import verify_cosserat as verify_cosserat
from crtraj.app.plan import ProblemPlan as ProblemPlan
from crtraj.app.plan import plan_problem as plan_problem
from crtraj.app.plan_motion import admit_plan as admit_plan
from crtraj.app.run_output import write_run as write_run
from crtraj.control.horizon._options import ReplanOptions as ReplanOptions
from crtraj.control.horizon._replanner import Replanner as Replanner
from crtraj.control.loop._closed_loop import ClosedLoop as ClosedLoop
from crtraj.control.loop._options import LoopOptions as LoopOptions
from crtraj.control.loop._run_record import ReplanRun as ReplanRun
from crtraj.control.tracking._options import TrackingOptions as TrackingOptions
from crtraj.core.errors import AdmissionError as AdmissionError
from crtraj.core.errors import InputError as InputError
from crtraj.hardware.actuators import Actuators as Actuators
from crtraj.hardware.admission import AdmittedMotion as AdmittedMotion
from crtraj.hardware.admission import admit as admit
from crtraj.hardware.sim._device import Faults as Faults
from crtraj.hardware.sim._device import SimDevice as SimDevice
from crtraj.hardware.stream._options import StreamOptions as StreamOptions
from crtraj.hardware.stream._streamer import Streamer as Streamer
from crtraj.hardware.stream._streamer import StreamReport as StreamReport
from crtraj.hardware.verify import FrameVerifier as FrameVerifier
from crtraj.io.problem import Problem as Problem
from crtraj.io.problem import Task as Task
from crtraj.io.problem import load_robot as load_robot
from crtraj.io.results import Result as Result
from crtraj.io.results import read_result as read_result
from crtraj.model.cosserat._statics import CosseratRod as CosseratRod
from crtraj.model.kinematics import Model as Model
from crtraj.model.mechanics import Mechanics as Mechanics
from crtraj.model.robot import Robot as Robot
from crtraj.planning.context import PlanningContext as PlanningContext
from crtraj.planning.options import PlannerOptions as PlannerOptions
from crtraj.planning.pipeline import ExecutablePlan as ExecutablePlan
from crtraj.planning.pipeline import plan_executable as plan_executable
from crtraj.planning.planners._registry import BUILTIN as BUILTIN
from crtraj.planning.planners._registry import make_planner as make_planner
from crtraj.planning.result import PlanResult as PlanResult
from crtraj.planning.result import PlanStatus as PlanStatus
from crtraj.planning.steer._options import SteerOptions as SteerOptions
from crtraj.planning.stop import StopCondition as StopCondition
from crtraj.viz.view import Visualizer as Visualizer
from crtraj.world.feed import ObstacleFeed as ObstacleFeed
from crtraj.world.obstacle import Obstacle as Obstacle
from crtraj.world.scene import Scene as Scene

__version__: str

__all__ = [
    "BUILTIN",
    "Actuators",
    "AdmissionError",
    "AdmittedMotion",
    "Calibration",
    "ClosedLoop",
    "CosseratRod",
    "ExecutablePlan",
    "Faults",
    "FrameVerifier",
    "InputError",
    "LoopOptions",
    "Mechanics",
    "Model",
    "Obstacle",
    "ObstacleFeed",
    "PlanResult",
    "PlanStatus",
    "PlannerOptions",
    "PlanningContext",
    "Problem",
    "ProblemPlan",
    "ReplanOptions",
    "ReplanRun",
    "Replanner",
    "Result",
    "Robot",
    "Scene",
    "SimDevice",
    "SteerOptions",
    "StopCondition",
    "StreamOptions",
    "StreamReport",
    "Streamer",
    "Task",
    "TrackingOptions",
    "Verification",
    "Visualizer",
    "__version__",
    "admit",
    "admit_plan",
    "admit_result",
    "calibrate_robot",
    "excitation_motion",
    "load_robot",
    "make_planner",
    "plan_executable",
    "plan_problem",
    "read_result",
    "record_dataset",
    "verify_cosserat",
    "write_run",
]
