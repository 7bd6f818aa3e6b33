"""Settings dataclasses (edge.refine.RefineSettings, edge.heading.HeadingSettings, ...) from what a
config file or a caller gives: off, on with the defaults, a dict of fields, or the dataclass itself."""
from dataclasses import fields


def settings_from(cls, value, what):
    """A settings dataclass from None/False (None), True (the defaults), a dict or an instance."""
    if value is None or value is False:
        return None
    if value is True:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, dict):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise ValueError(f"{what}: unknown setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        return cls(**value)
    raise ValueError(f"{what}: expected true/false, a dict of settings or {cls.__name__}, got {value!r}")
