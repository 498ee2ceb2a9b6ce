"""``python -m osmo.runtime.kubernetes.exec_relay SPEC``: ``osmo workflow exec`` into a pod.

What the Kubernetes runtime's ``exec`` gives the node to spawn (``osmo.worker.exec_process``,
which relays it over zenoh as on every node): this process runs the command in the pod's task
container through the API's exec (``Kube.exec``), and relays its own stdin to the command and
the command's stdout and stderr to its own; it exits with the command's exit code (1 with a
message when the API refuses). ``SPEC`` is JSON: kubeconfig, context, namespace, pod,
container, command, tty. It holds no secret.
"""

from __future__ import annotations

import json
import os
import select
import sys

__all__ = ["main"]


def main(argv: list[str]) -> int:
    """Relay one exec session (see the module docstring); its exit code."""
    from osmo.runtime.kubernetes.kube import KubeError, connect

    spec = json.loads(argv[0])
    try:
        kube = connect(spec.get("kubeconfig"), spec.get("context"))
        session = kube.exec(spec["namespace"], spec["pod"], spec["container"],
                            list(spec["command"]), tty=bool(spec.get("tty")))
    except KubeError as exc:
        sys.stderr.write(f"osmo: exec: {exc}\n")
        return 1
    stdin, out, err = sys.stdin.fileno(), sys.stdout.fileno(), sys.stderr.fileno()
    reading = True
    try:
        while session.open:
            if reading and select.select([stdin], [], [], 0)[0]:
                data = os.read(stdin, 65536)
                if data:
                    session.send(data)
                else:
                    reading = False
                    session.close_stdin()
            got_out, got_err = session.receive(0.05)
            if got_out:
                os.write(out, got_out)
            if got_err:
                os.write(err, got_err)
        return session.exit_code()
    finally:
        session.close()
        kube.close()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
