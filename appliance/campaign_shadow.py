"""A second configuration judged on a campaign drive's own inputs ("shadow mode").

Two campaigns with different configurations drive the same fields, but after their first
different decision the vehicles are in different places: every later false stop is a false
stop of another drive. On 12 drives with 3-5 false stops that divergence decides the totals as
much as the option does (docs/rgbd.md, "None within a metre of the front"). A shadow removes
it: the drive is driven by its own configuration, and every cycle the shadow configuration's
own pipelines and decision (fresh instances, their own state: novelty model, grid, tracks,
gate hold) see exactly the inputs the box saw -- the same frames, the same vehicle state -- and
its answer is scored against the same truth, but never drives. What one says and the other does
not, at the same moment on the same inputs, is the option's own doing.

What a shadow cannot show: what the vehicle would have done next under it (a shadow STOP does
not stop the vehicle; the next frames are the primary's). Closed-loop totals still come from a
campaign driven by the configuration itself.
"""
from __future__ import annotations

import logging

log = logging.getLogger("fieldguard.campaign")


class Shadow:
    """The pipelines and decision core of ``cfg`` (a parsed Config), stepped on each cycle's
    inputs of another loop (:meth:`step`)."""

    def __init__(self, cfg, primary_cfg=None):
        from appliance.decision import DecisionCore
        from appliance.perception import make_pipeline
        self.cfg = cfg
        # a shadow whose perception is the drive's own (the same pipelines with the same
        # options: only the decision differs) takes the drive's detections instead of running
        # the pipelines again on the same inputs: the same detections (the pipelines are
        # deterministic, docs/proving-ground.md "Determinism") for none of the cost, which on a
        # camera drive is most of it
        self.shared = primary_cfg is not None and cfg.perception == primary_cfg.perception
        self.pipelines = ([] if self.shared else
                          [make_pipeline(n, cfg) for n in cfg.perception.pipelines])
        # its novelty model boots as the daemon's does (a saved model where its config names
        # one: a campaign's --models-from), so a shadow of the drive's own configuration boots
        # with the drive's model; it never saves one
        from appliance import novelty_store
        novelty_store.load_into(self.pipelines)
        self.optional = set(cfg.perception.optional)
        self.core = DecisionCore(cfg)
        self.last_detections: dict = {}

    def step(self, res):
        """The shadow's (GateOutput, Picture or None, faults) for the primary loop's cycle ``res``:
        the primary's faults that are not its own pipelines' or fusion's (a stale camera is
        stale for both) plus the shadow's own."""
        from appliance.loop import run_pipeline
        inputs = res.inputs
        if self.shared:                        # the drive's own pipelines' detections and faults
            faults = [f for f in res.faults if not f.startswith("fusion failed")]
            detections = dict(res.detections)
        else:
            faults = [f for f in res.faults if not f.startswith(("pipeline ", "fusion failed"))]
            detections = {}
        for p in self.pipelines:
            optional = p.name in self.optional
            missing = p.missing(inputs)
            if missing:
                if not optional:
                    faults.append(f"pipeline {p.name}: no fresh {', '.join(missing)} data")
                continue
            d, msg = run_pipeline(p, inputs, "shadow pipeline")  # as the loop: a fault
            if d is not None:
                detections[p.name] = d
            elif not optional:
                faults.append(msg)
        try:
            picture = self.core.perceive(detections, inputs.vehicle, res.stamp_ns)
        except Exception as exc:
            log.exception("shadow fusion failed")
            faults.append(f"fusion failed: {type(exc).__name__}: {exc}")
            picture = None
        self.last_detections = detections      # what its pipelines said this cycle (for scoring)
        stamps = [getattr(s, "stamp_ns", None) for s in (inputs.stereo, inputs.rgbd, inputs.laser)]
        stamps = [s for s in stamps if s is not None]
        out = self.core.decide(res.stamp_ns, faults, picture, min(stamps) if stamps else None)
        return out, picture, faults

    def wait_idle(self, timeout_s: float = 600.0) -> None:
        """Wait for the shadow's novelty model updates (background threads) to finish, as the
        drive does for its own: the same answer on every run."""
        for p in self.pipelines:
            nd = getattr(p, "novelty", None)
            u = getattr(nd, "updater", None)
            if u is not None and not u.wait_idle(timeout_s):
                raise RuntimeError("the shadow's novelty model update did not finish in "
                                   f"{timeout_s:.0f} s")

    def close(self) -> None:
        for p in self.pipelines:
            close = getattr(p, "close", None)
            if close is not None:
                try:
                    close()
                except Exception:              # closing is best effort
                    log.exception("shadow pipeline %s: close failed", p.name)


def paired(primary: list[dict], shadow: list[dict], stop_times: dict[str, list[float]],
           window_s: float = 0.5) -> dict:
    """The two sides' stop onsets (``primary`` / ``shadow``: events with ``t_s`` and ``kind``)
    against the other side's STOP cycles (``stop_times["primary"]`` / ``["shadow"]``: the
    times of every cycle it said STOP): a false stop is *one side's only* when the other side
    said STOP in no cycle within ``window_s`` of its onset."""
    import bisect

    def near(times, t):
        i = bisect.bisect_left(times, t - window_s - 1e-9)
        return i < len(times) and times[i] <= t + window_s + 1e-9
    out = {}
    for side, evs, other in (("primary", primary, "shadow"), ("shadow", shadow, "primary")):
        times = stop_times[other]
        only = [e for e in evs if e["kind"] == "false" and not near(times, e["t_s"])]
        out[f"false_stops_{side}_only"] = len(only)
        out[f"false_stops_{side}_only_t_s"] = [e["t_s"] for e in only]
        true_only = [e for e in evs if e["kind"] == "true" and not near(times, e["t_s"])]
        out[f"true_stops_{side}_only"] = len(true_only)
        out[f"true_stops_{side}_only_t_s"] = [e["t_s"] for e in true_only]
    return out


def differences(results: list[dict]) -> list[dict]:
    """Where a campaign's drives and their shadow parted, drive by drive and in time: every
    false or true stop only one side made (:func:`paired`) and every stop the shadow missed
    (an obstacle in its own stop zone, no STOP), each ``{"drive", "t_s", "what"}``; the drive
    is ``KIND-SEED`` (its folder under ``drives/``). Results written before the true stops'
    times were kept give their false stops and misses only."""
    from appliance.campaign import drive_id
    whats = (("false_stops_primary_only_t_s", "false stop only the drive's own config made"),
             ("false_stops_shadow_only_t_s", "false stop only the shadow made"),
             ("true_stops_primary_only_t_s", "true stop only the drive's own config made"),
             ("true_stops_shadow_only_t_s", "true stop only the shadow made"))
    out = []
    for r in sorted(results, key=lambda r: (r["kind"], r["seed"])):
        sh = r.get("shadow")
        if not sh:
            continue
        drive, mine = drive_id(r["kind"], r["seed"]), []
        for key, what in whats:
            mine += [{"drive": drive, "t_s": t, "what": what} for t in sh.get(key, [])]
        for e in sh.get("events", []):
            if e.get("event") == "missed":
                # a miss the drive shared (it did not say STOP either) is no difference: said
                # so, so that the list reads as where the two parted
                state = e.get("primary_state", "?")
                head = ("missed by the shadow only" if state == "STOP" else
                        "missed by the shadow, not stopped for by the drive either")
                mine.append({"drive": drive, "t_s": e["t_s"],
                             "what": f"{head}: {e.get('obstacle', '?')} (the drive said "
                                     f"{state})"})
        out += sorted(mine, key=lambda d: d["t_s"])
    return out
