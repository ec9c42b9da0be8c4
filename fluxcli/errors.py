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


class InputError(UserError):
    """Numbers a science function was given cannot be used (a negative λ, a frame of another
    shape, a mesh with no volume).

    The science packages raise it for the checks they make on their inputs, so that a stage can
    catch exactly these (``except InputError``) and say which config key or file they came from,
    while a ValueError that numpy or scipy raises inside the same call (a bug) reaches the CLI
    with its traceback.  Uncaught, it is still a user error (exit 2, the science's message).
    """
