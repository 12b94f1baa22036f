"""Consent records: record a participant's consent, list records, withdraw a participant.

The register lives outside every dataset (owner-only permissions): --register DIR, else
$CRS_STUDY_CONSENT_DIR, else ~/.crs-study/consent. See consent/README.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from crs_study import consent
from crs_study._files import os_errors
from crs_study.commands import HelpFormatter
from crs_study.errors import ConsentError
from crs_study.paths import resolve_consent_form


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    def add(name: str, help_text: str) -> argparse.ArgumentParser:
        sub = actions.add_parser(name, help=help_text, description=help_text,
                                 formatter_class=HelpFormatter)
        # one name with `run --consent-register`; --register, its old name, still works
        sub.add_argument("--consent-register", "--register", dest="register", metavar="DIR",
                         default=None, help="consent register directory (default: "
                         "$CRS_STUDY_CONSENT_DIR or ~/.crs-study/consent)")
        return sub

    record = add("record", "record a participant's consent on a form")
    record.add_argument("--participant", metavar="ID",
                        help="pseudonymous label (letters and digits); generated when omitted")
    record.add_argument("--form", required=True, metavar="FILE",
                        help="the consent form signed (Markdown with a 'Version:' line), or "
                        "the shipped form's name, consent_form")
    record.add_argument("--experimenter", required=True, metavar="INITIALS",
                        help="initials of the experimenter taking consent")
    record.add_argument("--name", default=None,
                        help="the participant's name, kept in the register only (optional)")
    record.add_argument("--renew", action="store_true",
                        help="the participant consented before: this record replaces that "
                        "one (a new form version, a corrected name); the first is kept in "
                        "the register and `list` shows it (without --renew a second record "
                        "for a label is refused)")

    listing = add("list", "list consent records (names hidden unless --show-names)")
    listing.add_argument("--json", action="store_true", help="one JSON object per line")
    listing.add_argument("--show-names", action="store_true", help="include names")

    withdraw = add("withdraw", "withdraw a participant: remove all their data, keep an audit line")
    withdraw.add_argument("--participant", required=True, metavar="ID",
                          help="the participant's label, as in the consent register")
    withdraw.add_argument("--dataset", action="append", default=[], metavar="DIR",
                          help="dataset to remove the participant from (repeatable)")
    withdraw.add_argument("--register-only", action="store_true",
                          help="no dataset holds the participant's data: only mark the "
                               "consent record withdrawn")
    withdraw.add_argument("--dry-run", action="store_true",
                          help="print what would be removed (the paths and rows BIDS names "
                               "for the participant, the analysis outputs holding them) and "
                               "change nothing")
    withdraw.add_argument("--wait", type=float, default=0.0, metavar="SECONDS",
                          help="when a session of the participant is running: mark the "
                               "consent withdrawn (the session stops at its next trial) and "
                               "wait up to this long for it before removing the data")

    recover = add("recover", "finish a withdrawal that was interrupted")
    recover.add_argument("--dataset", action="append", required=True, metavar="DIR",
                         help="dataset whose interrupted withdrawal to finish (repeatable)")


def _line(record: consent.ConsentRecord, args: argparse.Namespace) -> str:
    name = f"  {record.name}" if args.show_names and record.name else ""
    return f"form {record.form_version:8s} {record.time}  {record.experimenter}{name}"


def _print_plan(plan: consent.DatasetWithdrawal, verb: str = "will") -> None:
    """The list of what a withdrawal removes, printed before it acts (or instead, dry run)."""
    lines = plan.lines()
    print(f"{plan.dataset}: withdrawing {plan.participant} {verb} "
          + ("remove:" if lines else "remove nothing here"), flush=True)
    for line in lines:
        print(f"  {line}", flush=True)


@os_errors(ConsentError)  # disk full, permission denied, a file where a folder should be: one line
def run(args: argparse.Namespace) -> int:
    register = consent.Register(args.register)
    if args.action != "recover" and register.directory.is_dir():
        for message in register.repair():  # a torn last line, set aside and said
            print(f"crs-study consent: repaired: {message}", file=sys.stderr, flush=True)
    if args.action == "record":
        form = consent.read_form(resolve_consent_form(args.form))
        record = register.record(form, args.experimenter, args.participant, args.name,
                                 renew=args.renew)
        renewed = f" (renews the record of {record.earlier[-1].time})" if record.earlier \
            else ""
        print(f"consent recorded: participant {record.participant}, form version "
              f"{record.form_version}, {record.time}, experimenter {record.experimenter}"
              f"{renewed}")
        return 0
    if args.action == "list":
        folder = register.directory
        if not folder.is_dir():  # a typo must not read as "no consent given"
            what = "is a file, not a folder" if folder.exists() else "no such folder"
            raise ConsentError(f"--consent-register {folder}: {what}; expected the consent "
                               "register's folder (the one `consent record` wrote)")
        records = register.records(past_unreadable=True)  # each unreadable line: a warning
        for record in records.values():
            row = asdict(record)
            for past in row["earlier"]:  # each a record of its own, without these two
                del past["earlier"], past["withdrawn_at"]
            for shown in (row, *row["earlier"]):
                if not args.show_names:
                    del shown["name"]
            row["status"] = record.status
            if args.json:
                print(json.dumps(row, sort_keys=True))
                continue
            for past in record.earlier:  # the history first, oldest first
                print(f"{record.participant:12s} {'renewed':10s} {_line(past, args)}")
            print(f"{record.participant:12s} {record.status:10s} {_line(record, args)}")
        if not records and not args.json:
            print(f"no consent records in {register.directory}")
        return 0
    if args.action == "withdraw":
        if bool(args.dataset) == args.register_only:
            raise ConsentError("withdraw needs --dataset DIR (each dataset holding the "
                               "participant's data) or, when none does, --register-only")
        if args.dry_run:
            for plan in consent.preview_withdrawal(args.participant, args.dataset):
                _print_plan(plan, "would")
            print(f"dry run: nothing was removed, and the consent record of "
                  f"{args.participant} is unchanged")
            return 0
        if not args.wait >= 0:
            raise ConsentError(f"--wait: expected seconds >= 0, got {args.wait!r}")
        entries = consent.withdraw(args.participant, args.dataset, register.directory,
                                   wait_s=args.wait, announce=_print_plan,
                                   progress=lambda line: print(line, flush=True))
        for entry in entries:
            print(f"withdrawn {entry['participant']} from {entry['dataset']}: "
                  f"{len(entry['removed'])} paths removed, rows removed from "
                  f"{len(entry.get('rows_removed_from', ()))} TSV(s), "
                  f"{len(entry.get('outputs_removed', ()))} analysis output(s) outside it")
            for note in entry.get("notes", ()):
                print(f"  note: {note}")
            if entry.get("outputs_removed") or any(
                    "derivatives" in path for path in entry["removed"]):
                print("  analysis results holding the participant were removed: re-run "
                      "crs-study analyze")
        print(f"consent record of {args.participant} marked withdrawn in {register.directory}")
        return 0
    for dataset in args.dataset:
        entry = consent.recover_withdrawal(dataset)
        print(f"{dataset}: " + (f"finished withdrawal of {entry['participant']}" if entry
                                else "no unfinished withdrawal"))
    return 0
