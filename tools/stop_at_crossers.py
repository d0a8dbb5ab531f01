"""[grid] stop_at and stop_chain against obstacles that cross into the path (hand-made cells, no
simulator): first STOP cycle and where the crosser was, papers' rule ("paper") against
stop_at 1.7 and stop_chain 3 (radius 0.3 m).

    python tools/stop_at_crossers.py
"""
import sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import numpy as np
from appliance.config import Config, GateConfig, GridConfig, ZonesConfig
from appliance.decision import DecisionCore
from appliance.perception import Detections
from hal import GateState
from hal.types import VehicleState
DT = 10**8
def body(xc, yc, w=0.45, d=0.3):
    xs = np.arange(xc - d/2, xc + d/2 + 1e-9, 0.05); ys = np.arange(yc - w/2, yc + w/2 + 1e-9, 0.05)
    g = np.array([[x, y] for x in xs for y in ys]); return g
for speed_w in (0.6, 1.2, 1.6, 3.0):
  for x0 in (6.0, 8.0, 10.0):
    res = {}
    for name, g in (("paper", GridConfig()), ("stop_at 1.7", GridConfig(stop_at=1.7)),
                    ("chain 3", GridConfig(stop_chain=3)), ("recur 1.3", GridConfig(stop_recur=1.3))):
        core = DecisionCore(Config(gate=GateConfig(hold_off_s=1.0), grid=g, zones=ZonesConfig(front_x_m=2.2)))
        first = None
        for k in range(60):
            xw = 2.2 + x0 - 2.5 * 0.1 * k      # walker's x in the vehicle frame (vehicle at 2.5 m/s)
            yw = 3.5 - speed_w * 0.1 * k
            pic = core.perceive({"s": Detections(points_xy=body(xw, yw))}, VehicleState(k*DT, k, speed_mps=2.5), k*DT)
            out = core.decide(k*DT, [], pic)
            if k > 10 and out.state is GateState.STOP and first is None:
                first = (k, round(xw - 2.2, 2), round(yw, 2))
        res[name] = first
    print('walker', speed_w, 'm/s, starts', x0, 'm ahead:', res)
