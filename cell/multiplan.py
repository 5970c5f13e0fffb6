"""Planning a task with several features: each feature's own shot by the one-shot planner (its
camera by the task's camera rule around its centre), every shot judged on every feature (the
coverage matrix, cell.coverage), and the fewest shots covering every coverable feature by
integer programming (cell.cover), ties broken by travel. A feature no shot covers is named
with the requirement that binds in its own plan: the plan is partial (not feasible), never
silently short of a feature."""
import time
from dataclasses import replace

import numpy as np

from cell import coverage, planner
from cell.cover import fewest_shots
from cell.plan import FeatureVerdict, Plan, PlannerSettings, Search


def travel(shots):
    """(S,) travel of each candidate shot [m]: its camera's distance from the candidates' mean
    camera position plus its lamp's from their mean lamp position. A linear stand-in for the
    arm's and the lamp's travel between the chosen shots (a tour's length is not linear in the
    choice): of equally few shots, those nearer the middle lie nearer each other."""
    cameras = np.array([s.camera_position for s in shots])
    lamps = np.array([s.lamp_position for s in shots])
    return (np.linalg.norm(cameras - cameras.mean(axis=0), axis=1)
            + np.linalg.norm(lamps - lamps.mean(axis=0), axis=1))


def plan_features(task, settings=PlannerSettings(), progress=None):
    """The Plan of a task's features (one or more): the chosen shots, each with the features it
    covers (Shot.covers), and per feature the shot covering it (Plan.features)."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    tasks = [task.with_feature(i) for i in range(len(task.features))]
    own = []
    for t in tasks:
        say(f"feature {t.feature.name}:")
        own.append(planner.plan(t, settings, progress=say))
    t_own = time.perf_counter()
    shots = [p.shot for p in own]
    judged = [[coverage.of_plan(t, p) if s == f else coverage.judge(t, p, shot) for s, shot in enumerate(shots)]
              for f, (t, p) in enumerate(zip(tasks, own))]
    covers = np.array([[c.covered for c in row] for row in judged])
    t_judge = time.perf_counter()
    distance = travel(shots)
    cover = fewest_shots(covers, distance)
    index = {s: k for k, s in enumerate(cover.chosen)}
    verdicts = []
    for f, (t, p) in enumerate(zip(tasks, own)):
        by = [s for s in cover.chosen if covers[f, s]]
        if not by:
            verdicts.append(FeatureVerdict(t.feature.name, None, p.binding, p.hint))
            continue
        best = f if f in by else min(by, key=lambda s: judged[f][s].worst)      # its own shot if chosen
        verdicts.append(FeatureVerdict(t.feature.name, index[best]))
    chosen = tuple(replace(shots[s], covers=tuple(judged[f][s] for f in range(len(tasks)) if covers[f, s]))
                   for s in cover.chosen)
    say(f"cover: {len(chosen)} of {len(shots)} shots cover {len(cover.coverable)} of {len(tasks)} features")
    uncovered = [(v, own[f]) for f, v in enumerate(verdicts) if v.covered_by is None]
    if uncovered:
        v, p = uncovered[0]
        binding, miss, hint = p.binding, p.miss, f"feature '{v.name}' is covered by no shot: {p.hint}"
    else:
        worst = max((r for shot in chosen for c in shot.covers for r in c.requirements), key=lambda r: r.value)
        binding, miss, hint = worst.name, worst.value - 1.0, ""
    timing = {"features": t_own - t0, "judge": t_judge - t_own, "cover": time.perf_counter() - t_judge,
              "total": time.perf_counter() - t0}
    search = Search(candidates=sum(p.search.candidates for p in own), starts=sum(p.search.starts for p in own),
                    refinements=tuple(r for p in own for r in p.search.refinements))
    notes = tuple(f"{t.feature.name}: {n}" for t, p in zip(tasks, own) for n in p.notes)
    return Plan(task_name=task.name, feasible=not uncovered, binding=binding, miss=miss, objective=cover.objective,
                hint=hint, shots=chosen, maps=None, settings=settings, scene=None, search=search,
                timing_s=timing, notes=notes, features=tuple(verdicts), plans=tuple(own),
                cover={"candidate_shots": len(shots), "covers": covers.tolist(), "travel_m": distance.tolist(),
                       "chosen": list(cover.chosen)})
