"""Rendering and training in one process, in either order (drake_grasp.core.native).

With torch's CUDA build (which brings triton), creating an optimizer after Drake's
VTK/EGL renderer had drawn a frame crashed the process with a segmentation fault: Mesa's
llvmpipe puts its libLLVM into the global symbol scope, and libtriton's LLVM bound to
it. Each sequence runs in a fresh interpreter, because the pytest process may have loaded
triton already, which would hide the crash; the check is the child's exit status.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_EPISODE = """
from drake_grasp.evaluation.episode import simulate_episode
from drake_grasp.config.scenario import load_scenario, replace

def render():
    s = replace(load_scenario(scenario_name="isolation", scenario_text="{policy: scripted}"),
                seed=0, visualize=False)
    r = simulate_episode(s).result
    assert r.sim_time_s > 1.0, r.sim_time_s
    print("rendered", flush=True)
"""

_TRAIN_STEP = """
import torch

def train_step():
    g = torch.Generator().manual_seed(0)
    from drake_grasp.cnn.network import DistanceCNN
    from drake_grasp.core.native import load_llvm_users_first
    load_llvm_users_first()
    model = DistanceCNN(generator=g)
    opt = torch.optim.SGD(model.parameters(), lr=1e-3, momentum=0.9)
    images = torch.rand(4, 1, 64, 64, generator=g)
    offsets = torch.rand(4, 2, 3, generator=g) * 0.1
    loss = model.forward_factored(images, offsets).abs().mean()
    loss.backward()
    opt.step()
    assert torch.isfinite(loss)
    print("trained", flush=True)
"""

_FOREIGN_RENDER = """
import numpy as np
from pydrake.geometry import (Box, ClippingRange, DepthRange, DepthRenderCamera,
    MakeRenderEngineVtk, PerceptionProperties, RenderCameraCore, RenderEngineVtkParams,
    SceneGraph, FramePoseVector)
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo, RgbdSensor
from pydrake.geometry import GeometryInstance, RenderLabel

def render():
    # Drake's renderer used directly, without drake_grasp's station.
    builder = DiagramBuilder()
    sg = builder.AddSystem(SceneGraph())
    sg.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    src = sg.RegisterSource("box")
    inst = GeometryInstance(RigidTransform([0, 0, 0.5]), Box(0.1, 0.1, 0.1), "box")
    props = PerceptionProperties()
    props.AddProperty("label", "id", RenderLabel(1))
    inst.set_perception_properties(props)
    sg.RegisterAnchoredGeometry(src, inst)
    core = RenderCameraCore("vtk", CameraInfo(64, 64, 1.0), ClippingRange(0.01, 2.0),
                            RigidTransform())
    cam = DepthRenderCamera(core, DepthRange(0.05, 2.0))
    sensor = builder.AddSystem(RgbdSensor(sg.world_frame_id(), RigidTransform(), cam))
    builder.Connect(sg.get_query_output_port(), sensor.query_object_input_port())
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    depth = sensor.depth_image_32F_output_port().Eval(sensor.GetMyContextFromRoot(ctx))
    assert np.isfinite(np.asarray(depth.data)).any()
    print("rendered", flush=True)
"""


def _run(body: str, *, timeout: float = 300) -> subprocess.CompletedProcess:
    code = textwrap.dedent(body)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    proc = subprocess.run([sys.executable, "-X", "faulthandler", "-c", code], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, (
        f"exit status {proc.returncode} (-11: killed by a segmentation fault)\n"
        f"stdout:\n{proc.stdout[-2000:]}\nstderr:\n{proc.stderr[-4000:]}")
    return proc


@pytest.mark.slow
def test_render_then_train_in_one_process():
    proc = _run(_EPISODE + _TRAIN_STEP + "\nrender()\ntrain_step()\n")
    assert proc.stdout.split() == ["rendered", "trained"]


@pytest.mark.slow
def test_train_then_render_then_train_in_one_process():
    proc = _run(_EPISODE + _TRAIN_STEP + "\ntrain_step()\nrender()\ntrain_step()\n")
    assert proc.stdout.split() == ["trained", "rendered", "trained"]


def test_training_after_a_render_by_other_code_in_one_process():
    """Mesa's LLVM is already loaded when drake_grasp first sees the process."""
    proc = _run(_FOREIGN_RENDER + _TRAIN_STEP + "\nrender()\ntrain_step()\n")
    assert proc.stdout.split() == ["rendered", "trained"]


def test_the_station_loads_triton_before_the_renderer():
    """Where triton is installed, building the station loads it before any frame is drawn
    (after that, any order is safe); where it is not, nothing is loaded."""
    import importlib.util

    has_triton = importlib.util.find_spec("triton") is not None
    proc = _run("""
        import sys
        from drake_grasp.objects import load_library
        from drake_grasp.config.scenario import load_scenario
        from drake_grasp.world.scene import make_scene
        from drake_grasp.world.station import MakeGraspStation
        s = load_scenario(scenario_name="isolation")
        lib = load_library(None)
        MakeGraspStation(s, make_scene(s.scene, 0, lib, s.plant), lib)
        print("triton" in sys.modules)
    """)
    assert proc.stdout.split()[-1] == str(has_triton)
