"""Errors that mean "the user gave bad input": the CLI turns them into exit code 2."""


class UserError(Exception):
    """Bad input (config key, file, argument, impossible geometry).

    The message is shown to the user as one paragraph, without a traceback; it must
    name the offending key, file or device and say what is wrong.
    """
