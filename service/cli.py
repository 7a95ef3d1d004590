"""`calib serve | worker | db upgrade | demo` (contract section 4), `import-urdf | export-urdf` (section 5)."""
from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from .config import Settings

HIDDEN_KINDS = ("joint_spring", "stiffening_spring", "hard_backlash", "soft_backlash", "gear_error", "encoder_scale",
                "rail_straightness", "cantilever", "elastic_bearings", "telescopic_bending", "thermal_growth", "base_tilt",
                "rehoming_step", "cable_force")
"""calib_world.KINDS, spelled out so that `calib --help` does not import numpy and scipy."""
INSTRUMENTS = ("laser_tracker", "optical", "motion_capture", "total_station")
"""calib_core.instruments.INSTRUMENTS, spelled out likewise (tests check that they agree)."""

ROOT = Path(__file__).resolve().parent.parent


def alembic_config(url: str):
    from alembic.config import Config

    cfg = Config(str(ROOT / "alembic.ini")) if (ROOT / "alembic.ini").exists() else Config()
    cfg.set_main_option("script_location", str(ROOT / "migrations"))
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    cfg.attributes["configure_logger"] = False
    return cfg


def db_upgrade(url: str, revision: str = "head") -> None:
    from alembic import command

    command.upgrade(alembic_config(url), revision)


def _logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def cmd_serve(args) -> int:
    from .config import check_token_setting

    settings = Settings.from_env()
    check_token_setting(settings)  # a setting it refuses: at once, before any import or process
    import uvicorn

    from . import processes

    processes.start_early()  # its imports beside the app's own and the migrations
    from .app import create_app

    if settings.is_sqlite:  # the embedded default: apply migrations on start
        db_upgrade(settings.database_url)
    # uvicorn shuts down gracefully on SIGTERM, then raises the signal again under the handler it found: by default
    # that kills the process before its exit handlers run, which left the fork server's socket directory
    # (/tmp/pymp-*) behind at every stop. Exiting instead runs them; the status is still 143 (128 + SIGTERM).
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level=args.log_level.lower(),
                timeout_graceful_shutdown=10)
    return 0


def _exit_on_sigterm(signum: int, frame) -> None:
    raise SystemExit(128 + signum)


def cmd_worker(args) -> int:
    from .db import Database
    from .queue.worker import Worker

    settings = Settings.from_env()
    if args.concurrency:
        from dataclasses import replace
        settings = replace(settings, worker_concurrency=args.concurrency)
    db = Database(settings.database_url)
    w = Worker(db, settings)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: w.stop())
    print(f"calib worker {w.id} on {db.engine.url.render_as_string(hide_password=True)}", flush=True)
    w.run()
    db.dispose()
    return 0


def cmd_db(args) -> int:
    settings = Settings.from_env()
    db_upgrade(settings.database_url, args.revision)
    print(f"database at {args.revision}")
    return 0


def cmd_demo(args) -> int:
    from .demo import run

    return run(args)


CONVERTIBLE = ("dlr_agile_justin", "hilti_trailblazer", "iiwa7_payload", "motoman_leica", "iiwa7_exp1", "iiwa7_exp2",
               "iiwa7_20161118", "agile_justin_right", "agile_justin_left")
"""`calib convert-dataset` names: the four dataset folders, the iiwa's other runs, the per-arm Justin chains (older)."""


def _dataset_readers(args) -> dict:
    from calib_core import datasets

    root = Path(args.root) if args.root else datasets.SHARED_DATASETS
    return {
        "dlr_agile_justin": lambda: datasets.agile_justin_tree(root, limits=args.limits),
        "hilti_trailblazer": lambda: datasets.hilti_trailblazer(root, setup_by=args.setup_by),
        "iiwa7_payload": lambda: datasets.iiwa7_payload(None, root, orientation=True, torques=True),
        "motoman_leica": lambda: datasets.motoman_leica(root),
        "iiwa7_exp1": lambda: datasets.iiwa7_run("exp1", root),
        "iiwa7_exp2": lambda: datasets.iiwa7_run("exp2", root),
        "iiwa7_20161118": lambda: datasets.iiwa7_run("20161118", root),
        "agile_justin_right": lambda: datasets.agile_justin("right", root),
        "agile_justin_left": lambda: datasets.agile_justin("left", root),
    }


def cmd_convert_dataset(args) -> int:
    """A third-party dataset (read from ../shared/datasets or --root, never copied into the repository) as contract
    model.json + measurements.csv (+ NOTES.txt: source, units, licence, what was widened); `all` writes the four
    datasets into OUTDIR/<name>/."""
    import json

    readers = _dataset_readers(args)
    names = CONVERTIBLE[:4] if args.name == "all" else (args.name,)
    for name in names:
        try:
            ds = readers[name]()
        except FileNotFoundError as exc:
            print(f"calib convert-dataset: {exc}", file=sys.stderr)
            return 2
        out = Path(args.outdir) / name if args.name == "all" else Path(args.outdir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "model.json").write_text(json.dumps(ds.model, indent=2) + "\n")
        (out / "measurements.csv").write_text(ds.csv_text)
        (out / "NOTES.txt").write_text(ds.notes + "\n")
        print(f"{out / 'model.json'}\n{out / 'measurements.csv'}\n{ds.notes}")
        noise = f" --instrument {ds.instrument}" if ds.instrument else ""
        print(f"try: calib demo --robot {out / 'model.json'} --data {out / 'measurements.csv'}{noise}")
    return 0


def cmd_import_urdf(args) -> int:
    """A URDF chain as contract model JSON (contract section 5)."""
    import json

    from calib_core.urdf import UrdfError, parse_urdf

    try:
        text = Path(args.file).read_bytes()
        doc = parse_urdf(text, args.base, args.target, length_unit=args.length_unit, angle_unit=args.angle_unit,
                         smr_m=args.smr)
    except OSError as exc:
        print(f"calib import-urdf: {exc}", file=sys.stderr)
        return 2
    except UrdfError as exc:
        for e in exc.errors:
            print(f"calib import-urdf: {args.file}: {e['field']}: {e['message']} (value: {e['value']!r})",
                  file=sys.stderr)
        return 1
    for note in doc["urdf"]["notes"]:
        print(f"calib import-urdf: {args.file}: note: {note}", file=sys.stderr)
    out = json.dumps(doc, indent=2) + "\n"
    if args.output:
        Path(args.output).write_text(out)
        ext = doc["urdf"]
        print(f"{args.output}: {len(doc['joints'])} joints ({', '.join(j['name'] for j in doc['joints'])}), "
              f"{ext['base_link']} -> {ext['target_link']}, units {doc['units']['length']}/{doc['units']['angle']}")
    else:
        sys.stdout.write(out)
    return 0


def cmd_export_urdf(args) -> int:
    """A model JSON, `GET /calibrations/{id}/model` or a calibration answer (`GET /calibrations/{id}`) as URDF."""
    import json

    from calib_core.urdf_write import to_urdf

    try:
        doc = json.loads(Path(args.file).read_text())
    except (OSError, ValueError) as exc:
        print(f"calib export-urdf: {args.file}: {exc}", file=sys.stderr)
        return 2
    if isinstance(doc, dict) and isinstance(doc.get("calibrated_model"), dict):  # a calibration answer
        findings = (doc.get("diagnosis") or {}).get("findings") or []
        model = {**doc["calibrated_model"], "calibration": {"effects": [
            {"kind": f.get("follows") if f.get("kind") == "correction" else f.get("kind"),
             "joints": f.get("joints") or []} for f in findings
            if (f.get("follows") if f.get("kind") == "correction" else f.get("kind")) in (doc.get("model") or [])
            and f.get("kind") != "unexplained"]}}
    else:
        model = doc
    if args.form != "rows" and model is doc and isinstance(doc, dict) and isinstance(doc.get("urdf"), dict) \
            and (args.source or (args.form == "original" or doc["urdf"].get("source"))):
        return _export_patched_urdf(args, doc)
    if args.form == "original" or args.base_joint:
        print(f"calib export-urdf: {args.file}: the original URDF can be patched from a model imported from a URDF "
              "(calib import-urdf, GET /calibrations/{id}/model), not from a calibration answer or a model written "
              "by hand", file=sys.stderr)
        return 1
    try:
        text = to_urdf(model, args.name)
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        return _export_failed(args, exc, "a contract model or calibration")
    if args.output:
        Path(args.output).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


def _export_failed(args, exc: Exception, what: str) -> int:
    """`export-urdf`'s error lines: each field of a ModelError (a ValueError), else why the file is not `what`."""
    from calib_core.model import ModelError

    if isinstance(exc, ModelError):
        for e in exc.errors:
            print(f"calib export-urdf: {args.file}: {e['field']}: {e['message']}", file=sys.stderr)
    else:
        print(f"calib export-urdf: {args.file}: not {what} ({exc})", file=sys.stderr)
    return 1


def _export_patched_urdf(args, doc: dict) -> int:
    """`export-urdf` of a model imported from a URDF: the original file patched (calib_core.urdf_patch) and its side
    file (`--side`, default next to `-o` as <name>.calibration.json)."""
    import json

    from calib_core.urdf_patch import export_calibrated_model

    source = None
    if args.source:
        try:
            source = Path(args.source).read_text(encoding="utf-8-sig")
        except OSError as exc:
            print(f"calib export-urdf: {exc}", file=sys.stderr)
            return 2
    side_path = Path(args.side) if args.side else (
        Path(args.output).with_suffix(".calibration.json") if args.output else None)
    try:
        out = export_calibrated_model(doc, source=source, base_joint=args.base_joint,
                                      side_ref=side_path.name if side_path else None)
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        return _export_failed(args, exc, "a contract model imported from a URDF")
    if args.output:
        Path(args.output).write_text(out.urdf, encoding="utf-8")
    else:
        sys.stdout.write(out.urdf)
    if side_path:
        side_path.write_text(json.dumps(out.side, indent=2) + "\n")
    print(f"calib export-urdf: the original URDF with the calibrated origins of {len(out.changed)} joints "
          f"({', '.join(out.changed) or 'none'}); "
          + (f"targets, base pose and effects in {side_path}" if side_path else
             "targets, base pose and effects not written (give --side FILE)"), file=sys.stderr)
    return 0


def cmd_plan(args) -> int:
    """Poses to measure (contract section 5, `POST /robots/{id}/plan`) as a CSV of the actuated joints, model units,
    that a robot program can run; `--data` plans after a measured set (diagnosis: after diagnosing it here)."""
    import json

    import numpy as np

    from calib_core.identify import identify
    from calib_core.io import MeasurementError, parse_measurements
    from calib_core.model import LENGTH_TO_MM, ModelError, parse_model
    from calib_core.plan import lookalike_pairs, plan, tracker_of

    from .plans.service import plan_csv

    try:
        model = parse_model(json.loads(Path(args.robot).read_text()))
        meas = parse_measurements(Path(args.data).read_bytes(), model) if args.data else None
    except OSError as exc:
        print(f"calib plan: {exc}", file=sys.stderr)
        return 2
    except (ModelError, MeasurementError, ValueError) as exc:
        print(f"calib plan: {args.data if isinstance(exc, MeasurementError) else args.robot}: {exc}", file=sys.stderr)
        return 1
    effects, rivals, robot = (), (), None
    if args.purpose == "diagnosis":
        if meas is None:
            print("calib plan: --purpose diagnosis needs --data (the measured set whose diagnosis lists look-alike "
                  "causes)", file=sys.stderr)
            return 2
        from calib_core.diagnosis import diagnose

        print(f"diagnosing {args.data} ({meas.n_poses} poses) ...", file=sys.stderr, flush=True)
        d = diagnose(model, meas, workers=Settings.from_env().diagnosis_workers)  # as an auto job runs it
        effects, robot = d.calibration.effects, d.calibration.robot
        rivals = lookalike_pairs(model, meas, effects, d.findings)
        if not rivals:
            print(f"calib plan: the diagnosis of {args.data} names no look-alike causes ({d.verdict()}): nothing to "
                  "split; plan geometric poses instead", file=sys.stderr)
            return 1
    elif meas is not None:
        robot = identify(model, meas, free=("base", "tool"), folds=0).robot
    tracker = None
    if args.tracker:
        tracker = np.array([float(v) for v in args.tracker.split(",")]) * LENGTH_TO_MM[model.length_unit]
    elif robot is not None:
        tracker = tracker_of(robot)
    try:
        p = plan(model, args.n, args.purpose, seed=args.seed, candidates=args.candidates, tracker_mm=tracker,
                 max_incidence_deg=args.max_incidence, meas=meas, effects=effects, rivals=rivals)
    except ValueError as exc:
        print(f"calib plan: {exc}", file=sys.stderr)
        return 1
    text = plan_csv(model, p)
    if args.out:
        Path(args.out).write_text(text)
    else:
        sys.stdout.write(text)
    g = p.observability["geometry"]
    print(f"{args.n} poses ({p.observability['criterion'].split(':')[0]}) -> {args.out or 'standard output'}; "
          f"planned vs random: condition number {g['planned']['condition_number']:.1f} vs "
          f"{g['random']['condition_number']:.1f}, observability index {g['planned']['observability_index']:.4f} vs "
          f"{g['random']['observability_index']:.4f}", file=sys.stderr)
    for r in p.observability.get("rivals", []):
        print(f"{r['found']} vs {r['look_alike']}: separation {r['planned']['separation_chi2']:.0f} (random poses: "
              f"{r['random']['separation_chi2']:.0f}, chi-square units)", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="calib", description="Robot calibration service")
    p.add_argument("--log-level", default="INFO")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve", help="API plus embedded workers")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.set_defaults(fn=cmd_serve)
    w = sub.add_parser("worker", help="a stand-alone worker (scale-out)")
    w.add_argument("--concurrency", type=int, default=0, help="pool processes (default CALIB_WORKER_CONCURRENCY)")
    w.set_defaults(fn=cmd_worker)
    d = sub.add_parser("db", help="database maintenance")
    dsub = d.add_subparsers(dest="db_cmd", required=True)
    up = dsub.add_parser("upgrade", help="apply migrations")
    up.add_argument("revision", nargs="?", default="head")
    up.set_defaults(fn=cmd_db)
    demo = sub.add_parser("demo", help="the whole story end to end: simulated robot (or your data), service, "
                          "calibration, diagnosis, validation, compensation, report",
                          description="Starts `calib serve` on the configured database (default sqlite:///./calib.db), "
                          "uploads a measurement campaign over REST, runs the auto calibration and tells the story.")
    demo.add_argument("--effect", choices=[*HIDDEN_KINDS, "none"],  # demo.EFFECTS (not imported: numpy)
                      help="the effect the simulated robot hides (default: drawn at random)")
    demo.add_argument("--seed", type=int, help="seed of the simulated robot (default: random, printed), "
                      "or of the validation split with --data (default 0)")
    demo.add_argument("--robot", metavar="MODEL.json", help="a contract model file: with --data, real measurements; "
                      "alone, a digital twin of that robot")
    demo.add_argument("--data", metavar="MEASUREMENTS.csv", help="a contract measurement CSV of that robot; "
                      "30 %% of the poses are held out for validation")
    demo.add_argument("--instrument", choices=INSTRUMENTS,
                      help="the noise model where the CSV has no sigma column (POST .../measurements?instrument=; "
                      "default: a laser tracker, assumed)")
    demo.add_argument("--limits", choices=["reject", "warn"], default="reject",
                      help="joint values outside the model's limits: reject the CSV (default) or accept them and "
                      "report the extent (POST .../measurements?limits=)")
    demo.add_argument("--report", default="calib-demo-report.html", metavar="PATH",
                      help="where to save the report (default ./calib-demo-report.html)")
    demo.add_argument("--keep-serving", action="store_true", help="leave the service running at the end (Ctrl-C stops it)")
    demo.set_defaults(fn=cmd_demo)
    cv = sub.add_parser("convert-dataset", help="write a real dataset of ../shared/datasets as contract model.json "
                        "and measurements.csv",
                        description="Converts a third-party dataset (read in place, never copied) into a contract "
                        "model.json, measurements.csv and NOTES.txt (source, units, licence, limits widened).")
    cv.add_argument("name", choices=[*CONVERTIBLE, "all"], help="the dataset; 'all': the four dataset folders, "
                    "each into OUTDIR/<name>/")
    cv.add_argument("outdir")
    cv.add_argument("--root", metavar="DIR", help="the folder holding the dataset folders (default ../shared/datasets "
                    "next to the repository, or CALIB_SHARED_DATASETS)")
    cv.add_argument("--limits", choices=["data", "vendor"], default="data",
                    help="dlr_agile_justin: vendor limits widened to what the data reach (default) or the vendor "
                    "limits as published (then upload with ?limits=warn / calib demo --limits warn)")
    cv.add_argument("--setup-by", choices=["file", "station"], default="file",
                    help="hilti_trailblazer: one base setup per recording (default) or per column height x IK "
                    "solution space (105 setups)")
    cv.set_defaults(fn=cmd_convert_dataset)
    iu = sub.add_parser("import-urdf", help="a URDF chain as contract model JSON (revolute, continuous, prismatic, "
                        "fixed joints; inertials as masses)")
    iu.add_argument("file", metavar="FILE")
    iu.add_argument("--base", metavar="LINK", help="the chain's base link (default: the URDF's root link)")
    iu.add_argument("--target", metavar="LINK[,LINK]", help="the measured points' links (default: the only leaf "
                    "link); several make the xyz form")
    iu.add_argument("--smr", metavar="X,Y,Z[;X,Y,Z]", help="the nominal SMR offset of each target in its link's frame, "
                    "metres, one triple per target in the order of --target (default: at the link's origin); write "
                    "--smr=-0.03,0,0.05 when it starts with a minus")
    iu.add_argument("--length-unit", choices=["m", "mm"], default="m", help="the model's length unit (default m)")
    iu.add_argument("--angle-unit", choices=["rad", "deg"], default="rad", help="the model's angle unit (default rad)")
    iu.add_argument("-o", "--output", metavar="MODEL.json", help="write here (default: standard output)")
    iu.set_defaults(fn=cmd_import_urdf)
    eu = sub.add_parser("export-urdf", help="a model or calibration JSON as URDF (identified geometry in the joint "
                        "origins; effects a URDF cannot hold listed in a comment)")
    eu.add_argument("file", metavar="CALIBRATION_OR_MODEL.json")
    eu.add_argument("--name", help="the URDF robot name (default: the model's)")
    eu.add_argument("-o", "--output", metavar="OUT.urdf", help="write here (default: standard output)")
    eu.add_argument("--form", choices=["original", "rows"], help="original: the URDF the model was imported from, "
                    "only the calibrated joint origins changed (the default for a model imported from a URDF, "
                    "e.g. GET /calibrations/{id}/model); rows: a URDF written from the model rows")
    eu.add_argument("--source", metavar="ROBOT.urdf", help="the original URDF, when the model does not carry it "
                    "(urdf.source)")
    eu.add_argument("--side", metavar="SIDE.json", help="form original: where to write the side file (targets in "
                    "their links, base poses, effects; default: next to -o as OUT.calibration.json)")
    eu.add_argument("--base-joint", nargs="?", const=True, default=None, metavar="LINK",
                    help="form original: add a root link (default name measurement_frame) fixed to the URDF's root "
                    "by the identified base pose")
    eu.set_defaults(fn=cmd_export_urdf)
    pl = sub.add_parser("plan", help="which poses to measure: a CSV of joint values a robot program can run",
                        description="Plans poses within the joint limits whose target faces the tracker: `geometric` "
                        "(D-optimal for the geometric parameters, load variety when the model has masses) or "
                        "`diagnosis` (the poses that best tell apart the look-alike causes the diagnosis of --data "
                        "names).")
    pl.add_argument("--robot", required=True, metavar="MODEL.json", help="a contract model file")
    pl.add_argument("--n", type=int, default=50, help="how many poses (default 50)")
    pl.add_argument("--purpose", choices=["geometric", "diagnosis"], default="geometric")
    pl.add_argument("--data", metavar="MEASUREMENTS.csv", help="a measured set: the plan adds to it (required for "
                    "diagnosis, which diagnoses it first)")
    pl.add_argument("--out", metavar="PLAN.csv", help="write here (default: standard output)")
    pl.add_argument("--seed", type=int, default=0, help="seed of the candidate poses (default 0)")
    pl.add_argument("--candidates", type=int, default=20000, help="random candidate poses (default 20000)")
    pl.add_argument("--tracker", metavar="X,Y,Z", help="tracker position in the robot base frame, model length unit "
                    "(default: where --data was measured from, else 3 m from the workspace centre)")
    pl.add_argument("--max-incidence", type=float, metavar="DEG", help="largest angle between the target's outward "
                    "direction and its line of sight to the tracker (default 60)")
    pl.set_defaults(fn=cmd_plan)
    args = p.parse_args(argv)
    _logging(args.log_level)
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
