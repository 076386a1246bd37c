"""``polrig info SESSION``: what a session holds, how each capture ended, its scores, and
whether every file still matches its SHA-256 checksum (exit code 1 if not). A reader: it takes
no lock (it may run while a capture writes the session) and writes nothing (a manifest of an
older schema version is migrated in memory only). A structurally damaged manifest is one line
naming the record (:func:`polrig.app.manifest.parse`, exit code 2)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="summarize a capture session and verify its checksums",
                       description="Summarize a capture session (plan, captures, statuses, "
                                   "scores, revisions) and re-check every file's SHA-256. "
                                   "Exit code 1 if a file is missing or changed.")
    p.add_argument("session", help="session folder (holds session.json)")
    p.add_argument("--no-verify", action="store_true", help="skip the checksum verification")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.acquisition.plan import PRIOR_MODES
    from polrig.app.manifest import describe_decision, describe_prior_scale
    from polrig.app.session import Session
    from polrig.solve.scoring import format_score

    s = Session.open(args.session)
    m = s.manifest
    plan = s.plan
    status = m["status"] + (f" ({m['status_reason']})" if m["status_reason"] else "")
    print(f"session {s.root}")
    print(f"  status: {status}")
    print(f"  created {m['created']}, updated {m['updated']}, polrig "
          f"{m['software']['version']}, conventions v{m['conventions_version']}")
    if s.stored_version != m["schema_version"]:  # migrated in memory: this command writes nothing
        print(f"  schema: version {s.stored_version}, read as version {m['schema_version']} "
              f"(the next capture --resume or reconstruct writes it so)")
    print(f"  rig: {'simulated' if m['rig']['simulated'] else 'hardware'}; calibration: "
          f"{m['calibration_id']}")
    md = m["metadata"]
    if not md.empty:  # who, why, what (manifest.SampleMetadata)
        print("  metadata: " + "; ".join(f"{k}: {v}" for k, v in md.header().items()))
    exposures = (",".join(f"{e:g}" for e in plan.exposures_us) + " us"
                 if plan.exposures_us else "camera default")
    seen = (f" (seen state {plan.seen_state}: {plan.states_deg[plan.seen_state]:g} deg)"
            if plan.mode == "hybrid" else "")
    if plan.mode == "adaptive":
        seen = (f" (target relative sigma {plan.target_sigma:g} on {100 * plan.target_share:g} % of the "
                f"object pixels, {plan.min_states} to {plan.max_states} states; the first state below, the others "
                f"chosen)")
    print(f"  plan: mode {plan.mode}{seen}, {len(plan.poses_deg)} poses, states "
          f"{','.join(f'{a:g}' for a in plan.states_deg)} deg, "
          f"{plan.frames_per_state} frame(s)/state, exposure {exposures}, "
          f"{plan.dark_frames} dark frame(s), demosaic {plan.demosaic}")
    processing = m["processing"]
    if processing is not None:  # absent before schema version 7
        scale = f", prior scale {processing['prior_scale']}" if plan.mode in PRIOR_MODES else ""
        print(f"  processing: models {processing['models']}{scale} (a resume goes on with these)")
    counts: dict[str, int] = {}
    for cap in s.captures:
        counts[cap["status"]] = counts.get(cap["status"], 0) + 1
    print("  captures: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())))
    set_aside: dict[int, list[dict]] = {}  # acquired captures a resume found damaged, acquired again
    for event in m["history"]:
        if event["event"] == "capture set aside":
            set_aside.setdefault(event["capture"], []).append(event)
    for cap in s.captures:
        n_raw = len(cap["files"].get("raw", []))
        n_dark = len(cap["files"].get("dark", []))
        line = (f"    [{cap['index']:3d}] pose {cap['pose_deg']:7.2f} deg  {cap['status']:8s} "
                f"{n_raw} raw, {n_dark} dark")
        results = [r for r in ("mueller", "truth_mueller") if r in cap["files"]]
        if results:
            line += ", " + ", ".join(results)
        if cap["reason"]:
            line += f"  ({cap['reason']})"
        print(line)
        for event in set_aside.get(cap["index"], ()):
            problems = event["problems"]
            more = f" and {len(problems) - 1} more" if len(problems) > 1 else ""
            print(f"          set aside ({event['time']}): {problems[0]}{more}; acquired again, "
                  f"the old folder kept in {event['kept']}")
        for d in cap.get("adaptive", ()):  # the states an adaptive capture took, why it stopped
            print(f"          decision: {describe_decision(d)}")
        n_states = s.states_taken(cap["index"])
        if "prior" in cap:
            print(f"          prior: {describe_prior_scale(cap['prior'], n_states)}")
        if cap["score"]:
            print(f"          score: {format_score(cap['score'])}")
        for name, rev in cap["revisions"].items():
            extra = f"  score: {format_score(rev['score'])}" if rev["score"] else ""
            if "prior" in rev:
                extra += f"  prior: {describe_prior_scale(rev['prior'], n_states)}"
            if rev["reason"]:
                extra += f"  ({rev['reason']})"
            print(f"          {name}: {rev['status']}{extra}")
    for rev in m["revisions"]:
        settings = ", ".join(f"{k} {rev[k]}" for k in ("mode", "demosaic", "calibration_id"))
        print(f"  revision {rev['name']} ({rev['created']}): {settings}")
    if args.no_verify:
        return 0
    problems = s.verify()
    n_files = sum(1 + ("meta_path" in rec) for _, _, rec in s.iter_file_records())
    if problems:
        print(f"  checksums: {len(problems)} problem(s) in {n_files} recorded files:")
        for line in problems:
            print(f"    {line}")
        return 1
    print(f"  checksums: all {n_files} files verified (SHA-256)")
    return 0
