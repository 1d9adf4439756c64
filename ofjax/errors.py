"""User-facing errors and the CLI wrapper that turns them into one line and exit code 2.

A `UserError` is a mistake in the user's input (a missing file, a corrupt image, poses that do not
fit, ...). Its message names the file or option and says what to do. `cli(main)` runs a CLI entry
point so that a `UserError` prints `ofjax: error: <message>` on stderr and exits with code 2, with
no traceback; anything else is a bug in ofjax and keeps its traceback.
"""

from __future__ import annotations

import functools
import sys
from typing import Callable

EXIT_USER_ERROR = 2


class UserError(Exception):
  """A problem with the user's input; the message is one line naming the file and the fix."""

  def __init__(self, message: str):
    # One line by contract, also where the message quotes a library's exception or a file's own
    # strings (a corrupt .sur's unit field can hold a newline): whitespace runs become one space.
    super().__init__(" ".join(str(message).split()))


def cli(main: Callable[..., int | None]) -> Callable[..., int]:
  """Wraps a CLI `main(argv)` so that user errors exit with code 2 and one line on stderr."""

  @functools.wraps(main)
  def wrapped(*args, **kwargs) -> int:
    try:
      return int(main(*args, **kwargs) or 0)
    except UserError as e:
      print(f"ofjax: error: {e}", file=sys.stderr)
      return EXIT_USER_ERROR
    except KeyboardInterrupt:
      print("ofjax: interrupted", file=sys.stderr)
      return 130

  return wrapped
