"""Write a zenoh client config with the user and password from the auth Secret filled in.

Run by the chart's init container:
render-client-config.py SOURCE USER_FILE PASSWORD_FILE DEST [USER_FILE PASSWORD_FILE DEST]...
SOURCE is the ConfigMap's client.json5 (plain JSON, a subset of JSON5); each DEST gets it with
the user and password before it (a kubernetes pool's worker also writes its pods' config).
DEST is written owner-only in a memory-backed volume, so the password never lands in a
ConfigMap or on disk.
"""

import json
import os
import sys


def main(source: str, user_file: str, password_file: str, dest: str) -> None:
    with open(source) as f:
        config = json.load(f)
    with open(user_file) as f:
        user = f.read().rstrip("\r\n")
    with open(password_file) as f:
        password = f.read().rstrip("\r\n")
    auth = config.setdefault("transport", {}).setdefault("auth", {})
    auth["usrpwd"] = {"user": user, "password": password}
    tmp = dest + ".tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(config, f, indent=2)
    os.replace(tmp, dest)


if __name__ == "__main__":
    if len(sys.argv) < 5 or (len(sys.argv) - 2) % 3:
        sys.exit("usage: render-client-config.py SOURCE USER_FILE PASSWORD_FILE DEST "
                 "[USER_FILE PASSWORD_FILE DEST]...")
    for at in range(2, len(sys.argv), 3):
        main(sys.argv[1], *sys.argv[at:at + 3])
