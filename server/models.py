"""Every table, for Alembic and for code that needs the whole schema."""

from server.db import Base
from server.jobs.models import BuildJob
from server.participants.models import ParticipantSession, PlaybackEvent, Trial, Vote
from server.researchers.models import Researcher
from server.security import KnownLogin, RateEvent
from server.stimuli.models import StimulusSet
from server.studies.models import Comparison, Stimulus, Study
from server.uploads.models import AnimationShare, StudyAsset

__all__ = ["AnimationShare", "Base", "BuildJob", "Comparison", "KnownLogin", "ParticipantSession", "PlaybackEvent",
           "RateEvent", "Researcher",
           "Stimulus", "StimulusSet", "Study", "StudyAsset", "Trial", "Vote"]
