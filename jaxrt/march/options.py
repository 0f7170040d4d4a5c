"""Validation shared by the march options (`SphereTracing`, `SoftShadow`)."""


def check_options(options, **rules):
    """Raise ValueError naming `Class(field=value)` where a rule fails. Rules:
    ("int", lo): an integer ≥ lo; ("num", lo): a number ≥ lo; ("num>", lo): a number > lo."""
    name = type(options).__name__
    for field, (kind, lo) in rules.items():
        value = getattr(options, field)
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and value == value
        if kind == "int":
            ok, expected = isinstance(value, int) and not isinstance(value, bool) and value >= lo, f"an integer ≥ {lo}"
        elif kind == "num":
            ok, expected = number and value >= lo, f"a number ≥ {lo}"
        else:
            ok, expected = number and value > lo, f"a number > {lo}"
        if not ok:
            raise ValueError(f"`{name}({field}={value!r})`: expected {expected}")
