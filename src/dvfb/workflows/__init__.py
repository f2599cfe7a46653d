"""What the commands run: pre-training, zero-shot and fine-tuning (one implementation each for a run
and a group of runs, docs/members.md), on the session core (:mod:`~dvfb.workflows.session`) and
the group (:mod:`~dvfb.workflows.group`); dataset export; the analyses that roll agents out (value,
exploration, video); the checks a command makes before it starts (resources); and the API of
``dvfb.load`` (:mod:`~dvfb.workflows.api`)."""
