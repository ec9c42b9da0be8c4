"""Errors that mean "the user gave bad input": the CLI turns them into exit code 2."""


class UserError(ValueError):
    """Bad input (config key, file, argument, impossible geometry).

    The message is shown to the user as one paragraph, without a traceback; it must
    name the offending key, file or device and say what is wrong.  It is the only
    exception the CLI maps to exit 2: a plain ``ValueError`` (or any other) reaching
    the CLI is a bug, shown with its traceback and exit 1.  It subclasses ValueError
    so code that catches ValueError (the science packages' word for "these numbers
    cannot be used") still catches it.
    """
