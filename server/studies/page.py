"""The participant page's own wording, its language and its device gate: the study file's ``[page]`` table.

Every string the page shows that is not one of the study's ``[texts]``, questions or answer labels is a field of
``Chrome``, with its English default here and nowhere else (participant.html carries no wording of its own; the
page fills every element from the study).  ``{name}`` placeholders are filled in by the page.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, field_validator

from server.security import refuse_bidi_controls

# Scripts written right to left (ISO 639-1): the page sets dir="rtl" for them.
RTL_LANGUAGES = frozenset({"ar", "dv", "fa", "he", "ks", "ku", "ps", "sd", "ug", "ur", "yi"})
Lang = Annotated[str, StringConstraints(pattern=r"^[a-z]{2,3}(-[A-Za-z0-9]{2,8})*$")]


class Strict(BaseModel):
    """The base of every table of a study file (here and in :mod:`server.studies.studyfile`): unknown fields
    refused, text stripped, no bidirectional controls."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=True)

    @field_validator("*")
    @classmethod
    def no_bidi_controls(cls, value: Any) -> Any:
        return refuse_bidi_controls(value)


def _s(default: str) -> str:
    return Field(default, min_length=1, max_length=300)


class Chrome(Strict):
    """The page's wording (English defaults)."""

    withdraw: str = _s("Withdraw and delete my answers")
    withdraw_confirm: str = _s("Withdraw from the study and delete all your answers?")
    about_title: str = _s("About this study")
    contact_label: str = _s("Contact:")
    next: str = _s("Continue")
    consent_title: str = _s("Consent")
    consent_agree: str = _s("I agree to take part.")
    start: str = _s("Start the study")
    questions_title: str = _s("Questions about you")
    instructions_title: str = _s("Instructions")
    keys_help: str = _s("Use the mouse, or the keys 1–5 to choose and Enter to submit. The vote button becomes "
                        "active once you have watched the clip play through.")
    begin: str = _s("Begin")
    progress: str = _s("Trial {index} of {total}")
    practice: str = _s("(practice, not counted)")
    loading: str = _s("Loading…")
    loading_percent: str = _s("Loading… {percent} %")
    play: str = _s("Play")
    submit: str = _s("Submit vote")
    watch_first: str = _s("Please watch the clip play through once.")
    saving: str = _s("Saving your vote…")
    saved: str = _s("Vote saved.")
    retrying: str = _s("Connection problem; retrying…")
    thanks_title: str = _s("Thank you")
    completion_code: str = _s("Your completion code:")
    completion_link: str = _s("Return to the study platform")
    withdrawn_title: str = _s("Your answers have been deleted")
    withdrawn_text: str = _s("You have left the study. Nothing you answered is kept. Thank you for your time.")
    retry: str = _s("Try again")
    not_found_title: str = _s("Study not found")
    not_found_text: str = _s("This study does not exist. Please check the link.")
    closed_title: str = _s("Study closed")
    closed_text: str = _s("This study is not taking participants at the moment.")
    cannot_start_title: str = _s("Cannot start")
    load_failed_title: str = _s("The video could not be loaded")
    load_failed_text: str = _s("Please check your connection and try again.")
    gate_title: str = _s("This window is too small for the study")
    gate_text: str = Field("The two animations must be shown large enough to judge their motion. Please use a "
                           "computer or a larger window; on a tablet, try turning it sideways.",
                           min_length=1, max_length=1000)


class DeviceGate(Strict):
    """Below this, the participant sees ``gate_text`` and cannot start (checked again on resize/rotation)."""

    min_scale: float = Field(0.8, gt=0, le=1, description="smallest allowed scale of the pair video (each "
                             "character at >= this share of its rendered width and height)")


class Page(Strict):
    lang: Lang = Field("en", description="the page's language (BCP 47, e.g. sv, ar); right-to-left scripts are "
                       "laid out right to left")
    chrome: Chrome = Field(default_factory=Chrome)
    device_gate: DeviceGate = Field(default_factory=DeviceGate)
    fullscreen: bool = Field(False, description="ask for full screen when the first trial starts (the participant "
                             "may refuse); each time full screen is left, a `fullscreen_exit` event is stored and "
                             "every vote records whether it was cast in full screen")

    @property
    def dir(self) -> str:
        return "rtl" if self.lang.split("-")[0] in RTL_LANGUAGES else "ltr"

    def public(self) -> dict[str, object]:
        """What the participant page reads (every string filled, defaults included)."""
        return {"lang": self.lang, "dir": self.dir, "chrome": self.chrome.model_dump(),
                "device_gate": self.device_gate.model_dump(), "fullscreen": self.fullscreen}
