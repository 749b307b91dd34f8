"""``atlas-onboard preflight``: the bench check before the first flight, and the checks it judges with."""
