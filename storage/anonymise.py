"""Anonymisation before anything is written: subject ids become keyed pseudonyms, one key per
tenant, and subject attributes are typed values from a fixed table, never free text.

    secret = load_or_create_secret(secret_file=None, env=os.environ, data_root=data_root)
    anonymiser = Anonymiser(secret)
    pseudonym = anonymiser.pseudonym("patient-4711", tenant="lab-a")   # 64 hex digits
    anonymiser.check_attributes({"sex": "F", "age": "43", "height_m": "1.83"})
    # -> {"sex": "F", "age_band": "40-44", "height_m": "1.85"}
    anonymiser.check_attributes({"name": "Jane"})   # InvalidArgument naming "name"

The pseudonym is HMAC-SHA256 keyed with a key derived from a server secret for the tenant, so that
pseudonyms of one tenant's subjects say nothing about another's (a tenant is told its own
pseudonyms, and could otherwise test candidate ids against every other tenant's data). The secret
is kept apart from the data (a 0600 key file outside the data root, or the environment), so that
the data alone cannot be matched back to ids by hashing candidate ids. Nothing else about the
client (address, host name) is ever stored.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import secrets
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Final

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.key_files import check_private_file
from jitdyn.storage.layout import fsync_dir

__all__ = [
    "ATTRIBUTES",
    "DEFAULT_ALLOWED",
    "DEFAULT_ALLOWED_ATTRIBUTES",
    "MAX_ATTRIBUTE_LENGTH",
    "MAX_SUBJECT_ID_LENGTH",
    "SECRET_BYTES",
    "Anonymiser",
    "default_secret_file",
    "load_or_create_secret",
]

# The attributes biomechanics needs to interpret a session, each a typed value that identifies no
# one alone: a word from a fixed vocabulary, or a number coarsened on the way in.
SEXES: Final = ("F", "M", "X")  # X: other or not stated
SIDES: Final = ("left", "right", "both")
LIMBS: Final = ("arm", "forearm", "hand", "leg", "thigh", "shank", "foot", "trunk", "neck", "head")
CONDITIONS: Final = (
    "healthy",
    "amputation",
    "stroke",
    "spinal-cord-injury",
    "cerebral-palsy",
    "parkinsons",
    "multiple-sclerosis",
    "osteoarthritis",
    "acl-reconstruction",
    "other",
)
AGE_BAND_YEARS: Final = 5
HEIGHT_STEP_M: Final = 0.05
MASS_STEP_KG: Final = 5.0
DEFAULT_ALLOWED_ATTRIBUTES: Final = frozenset(
    {"sex", "age", "age_band", "height_m", "mass_kg", "side", "limb", "condition"}
)
DEFAULT_ALLOWED: Final = DEFAULT_ALLOWED_ATTRIBUTES
# A value longer than this is not looked at further (a number or a word of the vocabularies is short).
MAX_ATTRIBUTE_LENGTH: Final = 32
MAX_SUBJECT_ID_LENGTH: Final = 256
SECRET_BYTES: Final = 32
ENV_SECRET: Final = "JITDYN_SECRET"
ENV_SECRET_FILE: Final = "JITDYN_SECRET_FILE"


def default_secret_file(env: Mapping[str, str]) -> Path:
    """`$XDG_CONFIG_HOME/jitdyn/secret.key`, else `~/.config/jitdyn/secret.key`."""
    config_home = env.get("XDG_CONFIG_HOME")
    base = Path(config_home) if config_home else Path(env.get("HOME") or Path.home()) / ".config"
    return base / "jitdyn" / "secret.key"


def _parse_secret(text: str, *, origin: str) -> bytes:
    try:
        secret = bytes.fromhex(text.strip())
    except ValueError as exc:
        raise InvalidArgument(f"{origin} must hold the secret as hex digits: {exc}") from exc
    if len(secret) < SECRET_BYTES:
        raise InvalidArgument(
            f"{origin} must hold at least {SECRET_BYTES} bytes ({2 * SECRET_BYTES} hex digits), got {len(secret)}"
        )
    return secret


def _create_secret(path: Path) -> None:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return  # another process created it first; use theirs
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_bytes(SECRET_BYTES).hex() + "\n")
        f.flush()
        os.fsync(f.fileno())
    fsync_dir(path.parent)


def load_or_create_secret(
    *, secret_file: Path | None, env: Mapping[str, str], data_root: Path | None = None
) -> bytes:
    """The server's pseudonymisation key.

    `JITDYN_SECRET` in `env` (hex) wins. Otherwise the key file: `secret_file`, else
    `JITDYN_SECRET_FILE` in `env`, else `default_secret_file(env)`; created with 32 random bytes and
    mode 0600 when missing. Refused (FailedPrecondition) when others could read or change the file
    (jitdyn.key_files), or lies inside `data_root`: a key stored with the data protects nothing.
    """
    if env.get(ENV_SECRET):
        return _parse_secret(env[ENV_SECRET], origin=f"environment variable {ENV_SECRET}")
    if secret_file is None:
        secret_file = Path(env[ENV_SECRET_FILE]) if env.get(ENV_SECRET_FILE) else default_secret_file(env)
    path = secret_file.expanduser().absolute()
    if data_root is not None:
        root = data_root.expanduser().resolve()
        if path.resolve().is_relative_to(root):
            raise FailedPrecondition(
                f"the secret file {path} is inside the data root {root}; keep the key apart from the "
                f"data: move it elsewhere (e.g. {default_secret_file(env)}) or set {ENV_SECRET}"
            )
    if not path.exists():
        _create_secret(path)
    check_private_file(path, setting="the secret file")
    return _parse_secret(path.read_text(), origin=f"the secret file {path}")


def _word(
    vocabulary: tuple[str, ...], *, fold: Callable[[str], str] = str.lower
) -> Callable[[str], tuple[str, str]]:
    def parse(value: str) -> tuple[str, str]:
        word = fold(value.strip())
        if word not in vocabulary:
            raise ValueError(f"one of {', '.join(vocabulary)}")
        return "", word

    return parse


def _number(text: str, *, low: float, high: float, unit: str) -> float:
    try:
        number = float(text)
    except ValueError:
        raise ValueError(f"a number of {unit} in [{low:g}, {high:g}]") from None
    if not (math.isfinite(number) and low <= number <= high):
        raise ValueError(f"a number of {unit} in [{low:g}, {high:g}]")
    return number


def _band(low: int) -> str:
    return f"{low}-{low + AGE_BAND_YEARS - 1}"


def _age(value: str) -> tuple[str, str]:
    text = value.strip()
    if not text.isdigit() or int(text) > 130:
        raise ValueError("whole years, 0 to 130 (stored as a 5-year band)")
    years = int(text)
    return "age_band", _band(years - years % AGE_BAND_YEARS)


def _age_band(value: str) -> tuple[str, str]:
    low, dash, high = value.strip().partition("-")
    if not (dash and low.isdigit() and high.isdigit()) or int(low) % AGE_BAND_YEARS or int(low) > 130:
        raise ValueError('a 5-year band such as "40-44"')
    if _band(int(low)) != value.strip():
        raise ValueError('a 5-year band such as "40-44"')
    return "", value.strip()


def _rounded(
    step: float, *, low: float, high: float, unit: str, digits: int
) -> Callable[[str], tuple[str, str]]:
    def parse(value: str) -> tuple[str, str]:
        number = _number(value, low=low, high=high, unit=unit)
        return "", f"{round(number / step) * step:.{digits}f}"

    return parse


# Every attribute a server can keep: name -> parser of the client's text into (the name it is
# stored under, "" for the same; the stored value), raising ValueError with what was expected.
ATTRIBUTES: Final[Mapping[str, Callable[[str], tuple[str, str]]]] = {
    "sex": _word(SEXES, fold=str.upper),
    "age": _age,
    "age_band": _age_band,
    "height_m": _rounded(HEIGHT_STEP_M, low=0.3, high=2.6, unit="metres", digits=2),
    "mass_kg": _rounded(MASS_STEP_KG, low=1.0, high=400.0, unit="kilograms", digits=0),
    "side": _word(SIDES),
    "limb": _word(LIMBS),
    "condition": _word(CONDITIONS),
}

_KEY_LABEL: Final = b"jitdyn pseudonym key v1\x00"


class Anonymiser:
    """Pseudonyms and attribute filtering with one secret and one allow-list."""

    def __init__(self, secret: bytes, allowed_attributes: Iterable[str] = DEFAULT_ALLOWED_ATTRIBUTES) -> None:
        if len(secret) < SECRET_BYTES:
            raise InvalidArgument(f"secret must have at least {SECRET_BYTES} bytes, got {len(secret)}")
        allowed = frozenset(allowed_attributes)
        unknown = sorted(allowed - ATTRIBUTES.keys())
        if unknown:
            raise InvalidArgument(
                f"allowed attributes must be typed ones of {', '.join(sorted(ATTRIBUTES))}, got {unknown}"
            )
        self._secret = secret
        self._allowed = allowed
        self._keys: dict[str, bytes] = {}

    @property
    def allowed_attributes(self) -> frozenset[str]:
        return self._allowed

    def tenant_key(self, tenant: str) -> bytes:
        """The tenant's pseudonym key: HMAC-SHA256 of a label and the tenant under the secret."""
        key = self._keys.get(tenant)
        if key is None:
            key = hmac.new(self._secret, _KEY_LABEL + tenant.encode("utf-8"), hashlib.sha256).digest()
            self._keys[tenant] = key
        return key

    def pseudonym(self, subject_id: str, *, tenant: str) -> str:
        """HMAC-SHA256 of the id under the tenant's key, as 64 hex digits; "" for no subject ("")."""
        if not subject_id:
            return ""
        if len(subject_id) > MAX_SUBJECT_ID_LENGTH:
            raise InvalidArgument(
                f"subject.id must have at most {MAX_SUBJECT_ID_LENGTH} characters, got {len(subject_id)}"
            )
        return hmac.new(self.tenant_key(tenant), subject_id.encode("utf-8"), hashlib.sha256).hexdigest()

    def check_attributes(self, attributes: Mapping[str, str]) -> dict[str, str]:
        """The attributes as stored: each checked against its type and coarsened (age banded, height
        and mass rounded). Raises InvalidArgument naming the first attribute that is not on the
        allow-list or whose value is not of its type."""
        kept: dict[str, str] = {}
        for key in sorted(attributes):
            value = attributes[key]
            where = f"open.subject.attributes[{key[:40]!r}]"
            if key not in self._allowed:
                raise InvalidArgument(
                    f"{where}: not an attribute this server keeps; allowed: {', '.join(sorted(self._allowed))}"
                )
            if len(value) > MAX_ATTRIBUTE_LENGTH:
                raise InvalidArgument(
                    f"{where} must have at most {MAX_ATTRIBUTE_LENGTH} characters, got {len(value)}"
                )
            try:
                name, stored = ATTRIBUTES[key](value)
            except ValueError as error:
                raise InvalidArgument(f"{where} must be {error}, got {value[:40]!r}") from None
            kept[name or key] = stored
        return kept
