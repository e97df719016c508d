"""The `drivedegrade` command: spec, preview, world, verify, reproduce, keygen, sign, merge, compare, estimate,
closed-loop import, analyse, ladder.

Each subcommand's argument parser lives here; its work lives in the module that owns the stage, imported
only when that subcommand runs. A user mistake prints one `drivedegrade: error: ...` line and exits 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ..errors import DriveDegradeError
from .keys import signing_key


def _spec(args: argparse.Namespace) -> int:
    from ..corruptions.spec import render_spec

    text = render_spec(args.format)
    if args.out:
        from ..atomic import atomic_write_text

        atomic_write_text(args.out, text)
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def _preview(args: argparse.Namespace) -> int:
    from ..corruptions.preview import write_preview

    path = write_preview(args.images, severity=args.severity, family=args.family, out=args.out,
                         seed=args.seed, width=args.width)
    print(f"wrote {path}", file=sys.stderr)
    return 0


def _world(args: argparse.Namespace) -> int:
    from ..data.world import cli_world

    return cli_world(args)


def _verify(args: argparse.Namespace) -> int:
    """Exit 0 when the certificate is intact (and signed by --public-key's key when given) and its arithmetic
    adds up, 1 when it was edited, its signature fails or its thresholds / axes / verdict disagree with its
    cells (naming how), 2 when unreadable, 3 when intact and consistent but incomplete."""
    from ..certificate.adaptive_check import check_adaptive
    from ..certificate.consistency import check_consistency, incompleteness
    from ..certificate.fields import isolation_text
    from ..certificate.seal import CertificateMismatch, verify
    from ..certificate.signing import UNSIGNED_TEXT, SignatureFailure, load_public_key, verify_signature

    public_key = load_public_key(args.public_key) if args.public_key else None
    try:
        cert = verify(args.file)
        signer = None if public_key is None else verify_signature(cert, public_key, where=args.file)
    except (CertificateMismatch, SignatureFailure) as exc:
        print(f"drivedegrade: verify: FAILED: {exc}", file=sys.stderr)
        return 1
    from ..certificate.adaptive_check import missing_results

    missing_files = missing_results(cert, Path(args.file).parent / "cells")
    if missing_files:  # not an edit: what verify needs is not there (exit 2, naming it)
        shown = ", ".join(map(str, missing_files[:5])) + (" ..." if len(missing_files) > 5 else "")
        print(f"drivedegrade: verify: cannot check {args.file}: an adaptive certificate is verified with its "
              f"per-frame results beside it, and these are missing: {shown}; copy the certificate together with "
              "its report folder's cells/ (as the run wrote it) and verify again", file=sys.stderr)
        return 2
    inconsistent = check_consistency(cert) + check_adaptive(cert, Path(args.file).parent / "cells")
    if args.baseline:  # a gate run's recorded test parts recomputed from the baseline itself
        from ..certificate.adaptive_check import check_gate_baseline

        inconsistent += check_gate_baseline(cert, Path(args.file).parent / "cells", Path(args.baseline))
    if inconsistent:
        print(f"drivedegrade: verify: FAILED: {args.file}: the digest verifies but the arithmetic does not add up "
              f"({len(inconsistent)} field(s)):", file=sys.stderr)
        for line in inconsistent:
            print(f"  {line}", file=sys.stderr)
        return 1
    what = f"planner {cert['planner'].get('name')!r}, verdict {cert['verdict'].get('label')}"
    if signer is not None:
        level = f"signature verifies: issued by the holder of the key with fingerprint {signer}"
    elif isinstance(cert.get("signature"), dict):
        level = (f"the signature was NOT checked: the certificate says it was signed by the key with fingerprint "
                 f"{cert['signature'].get('public_key_fingerprint')}, but anyone can write that; check who issued "
                 f"it with: drivedegrade verify {args.file} --public-key NAME.pub (the issuer's public key); "
                 "integrity only")
    else:
        level = f"{UNSIGNED_TEXT}: the digest catches an accidental edit, not a deliberate one"
    level = _imported_level(cert, level)
    missing = incompleteness(cert)
    if missing is not None:
        print(f"drivedegrade: verify: INCOMPLETE: {args.file}: intact and consistent, but the run is incomplete "
              f"(completeness.complete is false; {missing}): not a certificate of the whole ladder; {level}",
              file=sys.stderr)
        return 3
    print(f"{args.file}: OK, digest {cert['digest']} verifies, thresholds, axes and verdict agree with its cells "
          f"({what}); {level}")
    print(f"{args.file}: {isolation_text(cert)}")
    return 0


def _imported_level(cert: dict, level: str) -> str:
    """What an imported certificate proves, before its seal's level (unchanged for a run's certificate)."""
    from ..certificate.fields import IMPORTED_TEXT, imported_source, is_imported

    return f"{IMPORTED_TEXT} (from {imported_source(cert)}); {level}" if is_imported(cert) else level


def _reproduce(args: argparse.Namespace) -> int:
    """Exit 0 when every rerun cell is bit-identical to the certificate, 1 when one differs, 2 for a usage error
    (a missing file, a certificate that does not verify)."""
    from ..certificate.reproduce import reproduce
    from ..progress import Sink

    return reproduce(Path(args.certificate), Path(args.planner), n=args.cells, data=args.data,
                     salt=None if args.seed is None else str(args.seed), public_key=args.public_key, keep=args.keep,
                     any_planner=args.any_planner, closed_n=args.closed_cells, loop=args.loop, bar_sink=Sink())


def _keygen(args: argparse.Namespace) -> int:
    """Write NAME.key (private, mode 0600) and NAME.pub."""
    from ..certificate.signing import fingerprint, keygen, load_private_key

    key_path, pub_path = keygen(args.name)
    fp = fingerprint(load_private_key(key_path.read_bytes(), str(key_path)).public_key())
    print(f"wrote {key_path} (private: keep it secret, mode 0600) and {pub_path} (public key fingerprint {fp})")
    return 0


def _sign(args: argparse.Namespace) -> int:
    """Sign a finished run's certificate (issue 37 H1): this command runs no planner code, so the key never
    shares a process with one. Exit 0 signed, 1 when the certificate does not verify, 2 for a usage error."""
    from ..certificate.adaptive_check import check_adaptive
    from ..certificate.consistency import check_consistency
    from ..certificate.fields import isolation_text, planner_isolated
    from ..certificate.seal import CertificateMismatch, verify
    from ..certificate.signing import ENV_VAR
    from ..report.resign import sign_file

    key = signing_key(args, "--key")
    if key is None:
        raise DriveDegradeError(f"sign: no key: give --key PATH (from `drivedegrade keygen NAME`) or set {ENV_VAR}")
    try:
        cert = verify(args.file)
    except CertificateMismatch as exc:
        print(f"drivedegrade: sign: FAILED: not signed: {exc}", file=sys.stderr)
        return 1
    problems = check_consistency(cert) + check_adaptive(cert, Path(args.file).parent / "cells")
    if problems:
        print(f"drivedegrade: sign: FAILED: {args.file}: not signed: its arithmetic does not add up:", file=sys.stderr)
        for line in problems:
            print(f"  {line}", file=sys.stderr)
        return 1
    if not planner_isolated(cert):  # signed all the same: the signature says who issued it, verify shows how
        print(f"drivedegrade: sign: warning: {args.file}: {isolation_text(cert)}; a certificate to be published is "
              "best made with --drivedegrade-isolate (docs/explanation/trust-model.md)", file=sys.stderr)
    fingerprint, digest, written = sign_file(args.file, key)
    print(f"signed {args.file} with the key of fingerprint {fingerprint} (digest {digest}); wrote "
          f"{', '.join(map(str, written))}")
    return 0


def _merge(args: argparse.Namespace) -> int:
    """Join shard folders into one run's outputs; a missing shard is an error naming it (exit 2)."""
    from ..certificate.merge import merge_shards
    from ..progress import Sink
    from ..report.publish import publish
    from ..settings import shown_arg

    here = Path.cwd()
    command = "drivedegrade merge " + " ".join(shown_arg(a, here) for a in [*args.shards, "--out", args.out])
    key = signing_key(args)
    baseline = None
    if args.baseline:  # loaded first: a bad baseline is refused before anything is written
        from ..plugin.merge_gate import load_verified_baseline

        baseline = load_verified_baseline(Path(args.baseline), Path(args.baseline_public_key)
                                          if args.baseline_public_key else None)
    merged = merge_shards([Path(d) for d in args.shards], allow_incomplete=args.allow_incomplete,
                          command=command + (" --allow-incomplete" if args.allow_incomplete else ""), root=here,
                          progress=Sink())
    if merged.missing_cells and not args.allow_incomplete:  # issue 37 (low): it wrote them and exited 0
        raise DriveDegradeError(f"missing cell(s) {', '.join(merged.missing_cells)}: "
                                f"{merged.missing_advice or 'rerun the shard that lacks them'}; or pass "
                                "--allow-incomplete to write a certificate that says completeness: false")
    for line in publish(merged, Path(args.out), signing_key=key).lines:
        print(line)
    if key is not None and not merged.settings.isolate:  # as `sign` says it
        print("drivedegrade: merge: warning: signed a certificate whose planner was not isolated (planner isolated: "
              "no); a certificate to be published is best made with --drivedegrade-isolate", file=sys.stderr)
    if merged.cell_files:  # an adaptive run: verify recomputes its stops from the per-frame results beside it
        import shutil

        cells = Path(args.out) / merged.provenance.planner_name / "cells"
        cells.mkdir(parents=True, exist_ok=True)
        for cell, path in merged.cell_files.items():
            shutil.copyfile(path, cells / f"{cell}.json")
    if baseline is not None:
        from ..certificate.seal import load_certificate
        from ..plugin.merge_gate import gate_merged

        cert = load_certificate(Path(args.out) / merged.provenance.planner_name / "certificate.json")
        lines, failed = gate_merged(cert, baseline, args.tolerance)
        for line in lines:
            print(line)
        return 1 if failed else 0
    return 0


def _compare(args: argparse.Namespace) -> int:
    """Compare certificates: compare.csv and compare.html in --out; exit 2 for an unreadable, edited,
    inconsistent (verify's arithmetic) or incomparable certificate; an incomplete one is compared and marked."""
    from ..certificate.compare import write_compare
    from ..certificate.seal import CertificateMismatch

    try:
        csv_path, html_path, df = write_compare(args.certificates, args.out, force=args.force)
    except CertificateMismatch as exc:
        print(f"drivedegrade: compare: refused: {exc}", file=sys.stderr)
        return 2
    if df.attrs.get("note"):
        print(f"note: this comparison {df.attrs['note']}")
    for row in df.itertuples():
        flag = "  RANK REVERSAL with " + row.reversed_with if row.rank_reversal else ""
        flag += "" if row.status == "complete" else f"  INCOMPLETE ({row.status[len('incomplete: '):]})"
        flag += "  IMPORTED (metrics as given, plans not seen)" if getattr(row, "imported", False) else ""
        mixed = "recorded" in set(df["plan_movement"]) and row.plan_movement != "recorded"
        flag += "  (label on accuracy alone: no plan movement recorded, spec < 5)" if mixed else ""
        print(f"{row.planner}: clean L2 {row.clean_l2:.3f} (rank {row.rank_clean_l2}), mean retention rank "
              f"{row.rank_mean_retention}, verdict {row.verdict}, {row.ego_label}; intervals: "
              f"{row.interval_basis}{flag}")
    print(f"wrote {csv_path} and {html_path}", file=sys.stderr)
    return 0


def _estimate(args: argparse.Namespace) -> int:
    """Wall time of a certification from a planner's frames/s (and a certificate's measured overhead)."""
    from ..certificate.estimate import estimate, estimate_lines, overhead_per_prediction

    overhead = 0.0
    if args.certificate:
        from ..certificate.seal import verify

        overhead = overhead_per_prediction(verify(args.certificate).get("cost"))
    try:
        rows = estimate(args.fps, args.frames, args.gpus, cells=args.cells, overhead=overhead)
    except ValueError as exc:
        raise DriveDegradeError(f"estimate: {exc}") from None
    for line in estimate_lines(rows, args.fps, args.frames, args.cells, overhead):
        print(line)
    return 0


def _add_input_commands(sub: argparse._SubParsersAction) -> None:
    """spec, preview and world: what the suite injects, and the data it can render."""
    p = sub.add_parser("spec", help="emit the corruption ladder from the injector's own tables")
    p.add_argument("--format", choices=("yaml", "table", "json"), default="yaml")
    p.add_argument("--out", help="write to this file (atomically) instead of standard output")
    p.set_defaults(func=_spec)

    p = sub.add_parser("preview", help="render images under every family at one severity, or one family S1..S5")
    p.add_argument("images", nargs="+", help="image files (JPEG/PNG); the first is the montage's subject")
    p.add_argument("--severity", type=int, default=4, help="severity 1..5 for the all-family montage (default 4)")
    p.add_argument("--family", help="render this one family across S1..S5 instead")
    p.add_argument("--out", default="montage.png", help="output PNG (default montage.png)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=480, help="width of each montage tile in pixels (default 480)")
    p.set_defaults(func=_preview)

    p = sub.add_parser("world", help="render the embedded surround-view world in nuScenes format")
    p.add_argument("--out", required=True, help="output folder (the nuScenes data root)")
    p.add_argument("--scenes", type=int, default=None, help="number of scenes (default: the suite's default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--full-size", action="store_true", help="render 1600x900 instead of 800x450")
    p.add_argument("--train-images", action="store_true", help="also render the train split's images")
    p.add_argument("--future", type=int, choices=(3, 4), default=3,
                   help="seconds of future every scored frame holds: 3 (nuScenes, the default) or 4 (NAVSIM's eight "
                        "poses: for a planner declaring poses = 8)")
    p.add_argument("--junction-scenes", type=int, default=0, metavar="N",
                   help="add N scenes turning at a junction, in a split of their own (junction), rendered: the "
                        "frames a command label needs (--drivedegrade-split junction); default 0")
    p.set_defaults(func=_world)


def _add_run_commands(sub: argparse._SubParsersAction) -> None:
    """merge and estimate: a run split into shards, and what a run costs."""
    p = sub.add_parser("merge", help="join the shard folders of one run (--drivedegrade-shard I/N) into its outputs")
    p.add_argument("shards", nargs="+", metavar="SHARD_DIR", help="reports/<planner>/shard-I-of-N folders")
    p.add_argument("--out", required=True, help="output folder: writes <out>/<planner>/cells.csv, "
                                                "certificate.json and report.html")
    p.add_argument("--allow-incomplete", action="store_true",
                   help="merge although shards are missing; the certificate then says completeness: false")
    p.add_argument("--sign-key", metavar="PATH", help="sign the certificate with this Ed25519 private key "
                                                       "(default: $DRIVEDEGRADE_SIGNING_KEY, a path or the PEM text)")
    p.add_argument("--baseline", metavar="BASE", help="gate the merged run against this baseline certificate, as "
                                                     "--drivedegrade-baseline gates a whole run: exit 1 on a cell or "
                                                     "axis regression beyond --tolerance")
    p.add_argument("--tolerance", type=float, default=0.02, metavar="X",
                   help="the gate's tolerance on retention (default 0.02, as --drivedegrade-tolerance)")
    p.add_argument("--baseline-public-key", metavar="PUB", help="require the baseline to be signed by this key")
    p.set_defaults(func=_merge)

    p = sub.add_parser("estimate", help="wall time of a certification at a planner's frames/s on G GPUs")
    p.add_argument("--fps", type=float, required=True, help="the planner's frames per second on one GPU")
    p.add_argument("--frames", type=int, default=6019, help="scored frames (default 6019: nuScenes val)")
    p.add_argument("--cells", type=int, default=89, help="cells of the run (default 89: the full ladder and ego cells)")
    p.add_argument("--gpus", type=int, nargs="+", default=[1, 8, 64], help="GPU counts (default 1 8 64)")
    p.add_argument("--certificate", help="a certificate whose cost ledger gives the suite's per-frame overhead")
    p.set_defaults(func=_estimate)


def _add_certificate_commands(sub: argparse._SubParsersAction) -> None:
    """verify, reproduce, keygen and compare: checking, signing and comparing certificates."""
    p = sub.add_parser("verify", help="check a certificate's digest, signature and arithmetic: exit 0 intact, 1 "
                                      "edited, badly signed or inconsistent, 2 unreadable, 3 incomplete")
    p.add_argument("file", metavar="FILE", help="the certificate.json to check")
    p.add_argument("--public-key", metavar="PUB", help="also check the certificate's Ed25519 signature with this "
                                                       "public key (NAME.pub); an unsigned certificate then fails")
    p.add_argument("--baseline", metavar="BASE", help="an adaptive gate run: also recompute its gate's recorded "
                                                     "test parts from this baseline certificate (with its cells/)")
    p.set_defaults(func=_verify)

    p = sub.add_parser("reproduce", help="rerun clean, null and N sampled cells of a certificate and compare them bit "
                                         "for bit: exit 0 identical, 1 different, 2 usage error")
    p.add_argument("certificate", metavar="CERT", help="the certificate.json to check (verified first)")
    p.add_argument("planner", metavar="PLANNER", help="the planner file (.py) the certificate was made with")
    p.add_argument("--cells", type=int, default=3, metavar="N",
                   help="sampled cells besides clean and null (default 3; drawn by the certificate's digest and "
                        "--seed)")
    p.add_argument("--closed-cells", type=int, default=1, metavar="N",
                   help="closed-loop cells besides closed-clean, of a certificate that has them (default 1: each "
                        "drives every route under every seed; drawn like --cells)")
    p.add_argument("--loop", choices=("open", "closed", "both"),
                   help="rerun the open-loop cells, the closed-loop ones or both (default: the certificate's)")
    p.add_argument("--data", metavar="PATH", help="the data set's root when the certificate's is not on this "
                                                  "machine (default: the certificate's, or the embedded world)")
    p.add_argument("--seed", type=int, metavar="INT", help="the sample seed (default: fresh randomness, printed so "
                                                           "the same cells can be drawn again)")
    p.add_argument("--any-planner", action="store_true", help="rerun with a planner other than the certificate's "
                                                              "(name or fingerprint): compare its plans anyway")
    p.add_argument("--public-key", metavar="PUB", help="also check the certificate's Ed25519 signature")
    p.add_argument("--keep", action="store_true", help="keep the rerun's report folder (kept anyway when a cell "
                                                       "differs)")
    p.set_defaults(func=_reproduce)

    p = sub.add_parser("keygen", help="write an Ed25519 key pair NAME.key (mode 0600) and NAME.pub for signing")
    p.add_argument("name", metavar="NAME", help="path prefix of the two files")
    p.set_defaults(func=_keygen)

    p = sub.add_parser("sign", help="sign a finished run's certificate.json with an Ed25519 private key (runs no "
                                    "planner code; the run itself never holds the key)")
    p.add_argument("file", metavar="CERT", help="the certificate.json to sign (verified first; report.html beside "
                                                "it is updated)")
    p.add_argument("--key", metavar="PATH", help="the private key file from `drivedegrade keygen NAME` (default: "
                                                 "$DRIVEDEGRADE_SIGNING_KEY, a path or the PEM text)")
    p.set_defaults(func=_sign)

    p = sub.add_parser("compare", help="compare certificates: compare.csv and compare.html, ranks and reversals")
    p.add_argument("certificates", nargs="+", metavar="CERT", help="certificate.json files (verified first)")
    p.add_argument("--out", required=True, help="output folder for compare.csv and compare.html")
    p.add_argument("--force", action="store_true", help="compare certificates of different spec versions, data sets "
                                                        "or settings (never one whose arithmetic verify rejects)")
    p.set_defaults(func=_compare)


def build_parser() -> argparse.ArgumentParser:
    """The `drivedegrade` parser: one subparser per subcommand, added in the order `--help` lists them."""
    parser = argparse.ArgumentParser(prog="drivedegrade", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_input_commands(sub)
    _add_run_commands(sub)
    _add_certificate_commands(sub)
    from .imports import add_closed_loop_commands, add_foreign_commands

    add_closed_loop_commands(sub)
    add_foreign_commands(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except DriveDegradeError as exc:
        print(f"drivedegrade: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("drivedegrade: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
