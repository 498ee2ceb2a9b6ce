"""The Kubernetes runtime family: each attempt is a Pod of its task's image.

The node is ``osmo worker --runtime kubernetes --kubernetes-config FILE``: a worker that dials
out to the server like every worker and launches its attempts as pods of the cluster it runs
in (or whose kubeconfig it is given). One module per concern:

- ``config`` — the pool's configuration (:class:`KubePool`: namespace, node selectors per
  platform, tolerations, gang scheduler, security context, PriorityClasses, work volume),
  read from a JSON file;
- ``manifest`` — the Pod and Secret manifests of an attempt, pure (golden-tested);
- ``status`` — the one table from a pod's status to osmo's view of the attempt, as data;
- ``kube`` — the only module that imports the ``kubernetes`` client (an extra:
  ``pip install "osmo[kubernetes]"``); its errors become :class:`KubeError`;
- ``follow`` — one attempt's pod from its creation to its deletion: watch, logs, verdict;
- ``groups`` — gangs: the group's Service and PodGroup, ``{{host:NAME}}``, the lead first;
- ``runtime`` — :class:`KubernetesRuntime`, the runtime contract around all of these;
- ``capacity`` — what the node offers: the allocatable resources of the nodes it may use.

Importing this package imports no ``kubernetes`` module.
"""
