"""A study with its participants' counts: what its list, its dashboard and the command line show."""

from __future__ import annotations

from collections.abc import Mapping

from sqlalchemy.orm import Session

from server.analysis.screening import ParticipantScreening
from server.participants import service as participants
from server.participants.rows import screened_rows
from server.studies.models import Study, StudyState
from server.studies.schemas import StudySummary
from server.studies.service import screening_rules, trials_total


def participant_counts(session: Session, study: Study, include_pilot: bool = False,
                       records: Mapping[str, ParticipantScreening] | None = None) -> dict[str, int]:
    """:func:`server.participants.service.participant_counts`, screened by the study's rules: a rule other than
    the catch trials needs every participant's screening record (``records`` if the caller has them)."""
    if records is None and screening_rules(study).rules != ["catch"]:
        records = screened_rows(session, study, include_pilot)[1]
    return participants.participant_counts(session, study, include_pilot, records)


def study_summary(session: Session, study: Study) -> StudySummary:
    """The study as its list and the command line show it: state, owner, participant and vote counts, what may
    still be edited."""
    counts = participant_counts(session, study)
    never_opened = study.opened_at is None
    return StudySummary(slug=study.slug, title=study.title, state=study.state,
                        owner=study.owner.email if study.owner else None, started=counts["started"],
                        completed=counts["completed"], votes=participants.vote_count(session, study),
                        trials_total=trials_total(study), participant_url=f"/s/{study.slug}",
                        editable={"texts": never_opened, "recruitment": never_opened,
                                  "design": never_opened and study.state == StudyState.draft})
