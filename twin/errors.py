"""The one error type a user can fix (a bad file, option, port or angle): `vrscroll` prints it as one line
on stderr and exits with status 2, never with a traceback. Every layer may raise it; it imports nothing."""


class UserError(Exception):
    """Something the user can fix; printed without a traceback."""
