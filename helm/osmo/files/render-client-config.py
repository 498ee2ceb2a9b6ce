"""Write a zenoh client config with the user and password from the auth Secret filled in.

Run by the chart's init container: render-client-config.py SOURCE USER_FILE PASSWORD_FILE DEST.
SOURCE is the ConfigMap's client.json5 (plain JSON, a subset of JSON5). DEST is written
owner-only in a memory-backed volume, so the password never lands in a ConfigMap or on disk.
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
    if len(sys.argv) != 5:
        sys.exit("usage: render-client-config.py SOURCE USER_FILE PASSWORD_FILE DEST")
    main(*sys.argv[1:])
