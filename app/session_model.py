"""What every part of a session's state shares: its jobs, busy line and messages, and the
app's limits (no widget code, as in the other models put together in ExplorerState)."""

from __future__ import annotations

import param

from mdcore._pipeline import Method, Settings

from .glossary import in_app_words
from .jobs import JobRunner

# The app's own limits, tighter than the library's: each bounds the time and memory of one
# click (measured in docs/performance.md); the command line takes more.
#: Candidates per wave (library: 10⁷). A wave scores each at every observed input, in
#: chunks (memory does not grow), and later waves walk them through the earlier waves.
APP_MAX_CANDIDATES = 1_000_000
#: Simulator runs per wave (library: 10⁴). The emulator factorises runs × runs over all
#: waves so far.
APP_MAX_RUNS = 100
#: θ samples and φ per θ (library: 10⁵ each and 10⁸ pairs): at most 10⁶ (θ, φ) pairs, the
#: paper's largest (beam-2d: 1000 × 1000).
APP_MAX_N_S = APP_MAX_N_PHI = 1_000
#: Work of one run of scenario 3 and of KOH, in units of (θ, φ) pairs or chain steps ×
#: outputs × training rows³ (each pair or step factorises an N × N covariance per output):
#: beam-2d at the paper's sizes (10⁶ pairs × 64³ = 2.6 × 10¹¹, the paper chain
#: 150,000 × 64³ = 3.9 × 10¹⁰) is the most a built-in case asks for; an upload with many
#: training rows reaches these with smaller N_s × N_φ or the fast chain.
MAX_S3_WORK, MAX_KOH_WORK = 1e12, 4e10
#: What the app says when a value is beyond one of its limits.
APP_LIMITS = {
    "n_candidates": f"The app scores at most {APP_MAX_CANDIDATES:,} candidates per wave "
                    "(a wave then takes seconds); the command line takes up to 10,000,000.",
    "n_runs": f"The app runs at most {APP_MAX_RUNS} simulator runs per wave (its emulator "
              "factorises all runs × all runs); the command line takes up to 10,000.",
    "n_s": f"The app takes at most {APP_MAX_N_S:,} θ samples and {APP_MAX_N_PHI:,} φ per θ "
           "(10⁶ pairs, the paper's largest; a minute or so); the command line takes more.",
}
APP_LIMITS["n_phi"] = APP_LIMITS["n_s"]
#: Seconds per unit of work (above) of a KOH chain step and of a scenario-3 (θ, φ) pair
#: with the paper's prior proposal (each pair also joins the prediction), and a run's
#: fixed cost. The adaptive proposal (the default) predicts from a bounded number of
#: pairs, so each pair costs only its weight: SECONDS_PER_PAIR per pair and output plus
#: SECONDS_PER_ADAPTIVE_WORK per unit. Fitted to the app's runs of the built-in cases
#: (docs/performance.md, "Run estimates": bench/app_estimates.py).
SECONDS_PER_KOH_WORK, SECONDS_PER_S3_WORK, SECONDS_FIXED = 1.3e-9, 5e-10, 0.4
SECONDS_PER_PAIR, SECONDS_PER_ADAPTIVE_WORK = 1.4e-6, 6.2e-11
#: A run estimated longer than this says so on its button before it starts.
ANNOUNCE_SECONDS = 3.0


def estimate_seconds(n_train: int, n_out: int, *, koh_steps: int = 0,
                     s3_pairs: int = 0, proposal: str = "adaptive") -> float:
    """Rough seconds of a discrepancy run: each KOH chain step and each scenario-3 pair
    factorises an ``n_train`` × ``n_train`` covariance per output (cubic in ``n_train``;
    ``proposal`` "adaptive" or "prior", see above); scenarios 1 and 2 are in the fixed
    cost. Within about a factor of 2."""
    per = n_out * float(n_train) ** 3
    pair = (n_out * SECONDS_PER_PAIR + SECONDS_PER_ADAPTIVE_WORK * per
            if proposal == "adaptive" else SECONDS_PER_S3_WORK * per)
    return SECONDS_FIXED + SECONDS_PER_KOH_WORK * per * koh_steps + pair * s3_pairs


def work_problem(case, settings: Settings, methods) -> str | None:
    """Why the app will not run ``methods`` on ``case`` with ``settings`` (scenario 3 or
    KOH beyond :data:`MAX_S3_WORK` / :data:`MAX_KOH_WORK`), or None."""
    n = case.X_train.shape[0]
    per = case.n_out * float(n) ** 3
    if Method.S3 in methods and settings.n_s * settings.n_phi * per > MAX_S3_WORK:
        most = int(MAX_S3_WORK / per)
        return (f"Scenario 3 with N_s × N_φ = {settings.n_s * settings.n_phi:,} pairs on "
                f"{n} training rows × {case.n_out} output(s) is more than the app runs in "
                f"one go (minutes to hours): every pair factorises a {n} × {n} covariance. "
                f"Lower N_s × N_φ to at most {most:,}, or run it from the command line.")
    if Method.KOH in methods and settings.n_iter * per > MAX_KOH_WORK:
        return (f"KOH with a {settings.n_iter:,}-step chain on {n} training rows × "
                f"{case.n_out} output(s) is more than the app runs in one go (minutes to "
                f"hours): every step factorises a {n} × {n} covariance. Choose the fast "
                "chain, fewer training rows, or run it from the command line "
                "(python -m mdcore run … --methods koh).")
    return None


def allowed_values(p: param.Parameter) -> str:
    """What ``p`` accepts, in words: "a whole number from 1 to 100", "one of max, 2nd max"."""
    if isinstance(p, param.Selector):
        return "one of " + ", ".join(str(o) for o in p.objects)
    if not isinstance(p, param.Number):
        return "a value of the field's kind"
    kind = "a whole number" if isinstance(p, param.Integer) else "a number"
    lo, hi = p.bounds or (None, None)
    lo_in, hi_in = getattr(p, "inclusive_bounds", (True, True))
    hi = hi if hi is not None and hi <= 1e7 else None         # not a limit worth saying

    def num(v) -> str:
        return f"{int(v):,}" if float(v).is_integer() else f"{v:g}"

    if lo is not None and hi is not None and lo_in and hi_in:
        return f"{kind} from {num(lo)} to {num(hi)}"
    parts = []
    if lo is not None:
        parts.append(f"{'at least' if lo_in else 'greater than'} {num(lo)}")
    if hi is not None:
        parts.append(f"{'at most' if hi_in else 'less than'} {num(hi)}")
    return kind + (" " + " and ".join(parts) if parts else "")


class SessionModel(param.Parameterized):
    """The busy state of the session's one job at a time, and the messages it shows
    (``_jobs``, a :class:`~mdcore_app.jobs.JobRunner`, is set by ExplorerState)."""

    busy = param.Boolean(default=False)
    cancelled = param.Boolean(default=False, doc="Whether the last job was cancelled.")
    task = param.String(default="")
    progress = param.Number(default=0.0, bounds=(0.0, 1.0))
    progress_message = param.String(default="", doc="What the running job is doing.")
    error = param.String(default="", doc="Last error message (shown as a notification).")
    n_errors = param.Integer(default=0, doc="Counts errors, so a repeated message still fires.")
    notice = param.String(default="", doc="Last numerical warning (e.g. a low ESS).")
    n_notices = param.Integer(default=0)

    _jobs: JobRunner

    @property
    def background(self) -> bool:
        return self._jobs.background

    @property
    def jobs(self) -> JobRunner:
        """The session's job runner (its ``job`` is the newest job)."""
        return self._jobs

    def cancel(self) -> None:
        """Stop the running wave or discrepancy run; what it already showed stays."""
        if self._jobs.cancel():
            self.param.update(progress_message="cancelling …", cancelled=True)

    def reject(self, name: str, value, reason: Exception) -> None:
        """Report a typed value the parameter ``name`` refused (the field reverts): what is
        allowed and, for :data:`APP_LIMITS`, why; never param's message (it names the class)."""
        p = self.param[name]
        if name in APP_LIMITS and isinstance(value, int) and not isinstance(value, bool) \
                and value > p.bounds[1]:
            why = (f"{p.label}: {value:,} is not allowed (at most {p.bounds[1]:,}: "
                   f"{APP_LIMITS[name].rstrip('.')}).")
        else:
            shown = "an empty field" if value is None else repr(value)
            why = f"{p.label}: {shown} is not allowed ({allowed_values(p)})."
        self.report_error(f"{why} The field keeps {getattr(self, name)!r}.")

    def report_error(self, message: str) -> None:
        """Show ``message`` as one error notification."""
        self.param.update(error=message, n_errors=self.n_errors + 1)

    def _report_notice(self, message: str) -> None:
        # A method's advice: mdcore's option names as the app's labels (an error keeps its
        # names: a session file's key path, "controls.n_s", is what to fix).
        self.param.update(notice=in_app_words(message), n_notices=self.n_notices + 1)
