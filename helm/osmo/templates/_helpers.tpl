{{/*
Names, labels, endpoints and the pieces every osmo pod shares. File paths inside the pods:
  /var/lib/osmo        OSMO_HOME (server: the PVC; workers: an emptyDir)
  /etc/osmo/zenoh      the zenoh configs (ConfigMap): server.json5, client.json5, router.json5
  /run/osmo/zenoh      client.json5 with the user/password filled in (auth.enabled only)
  /etc/osmo/tls/server the server certificate Secret (ca.crt, tls.crt, tls.key)
  /etc/osmo/tls/client the client certificate Secret (mtls only)
  /etc/osmo/auth       the user/password Secret (user, password, dictionary; with the router
                       also server-user, server-password; with data-mode pods pod-user,
                       pod-password)
  /run/osmo/zenoh/pod.json5  the client config a kubernetes pool's worker hands its task pods
                       (auth.podUser; data-mode pools with auth.enabled only)
*/}}

{{- define "osmo.name" -}}
{{- default .Chart.Name .Values.nameOverride | trunc 63 | trimSuffix "-" -}}
{{- end -}}

{{- define "osmo.fullname" -}}
{{- if .Values.fullnameOverride -}}
{{- .Values.fullnameOverride | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- $name := default .Chart.Name .Values.nameOverride -}}
{{- if contains $name .Release.Name -}}
{{- .Release.Name | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- printf "%s-%s" .Release.Name $name | trunc 63 | trimSuffix "-" -}}
{{- end -}}
{{- end -}}
{{- end -}}

{{- define "osmo.chart" -}}
{{- printf "%s-%s" .Chart.Name .Chart.Version | replace "+" "_" | trunc 63 | trimSuffix "-" -}}
{{- end -}}

{{/* Labels on every object. */}}
{{- define "osmo.labels" -}}
helm.sh/chart: {{ include "osmo.chart" . }}
{{ include "osmo.selectorLabels" . }}
app.kubernetes.io/version: {{ .Chart.AppVersion | quote }}
app.kubernetes.io/managed-by: {{ .Release.Service }}
{{- with .Values.commonLabels }}
{{ toYaml . }}
{{- end }}
{{- end -}}

{{- define "osmo.selectorLabels" -}}
app.kubernetes.io/name: {{ include "osmo.name" . }}
app.kubernetes.io/instance: {{ .Release.Name }}
{{- end -}}

{{- define "osmo.serviceAccountName" -}}
{{- if .Values.serviceAccount.create -}}
{{- default (include "osmo.fullname" .) .Values.serviceAccount.name -}}
{{- else -}}
{{- default "default" .Values.serviceAccount.name -}}
{{- end -}}
{{- end -}}

{{- define "osmo.image" -}}
{{- printf "%s:%s" .Values.image.repository (default .Chart.AppVersion .Values.image.tag) -}}
{{- end -}}

{{/* Secret names: the existing one when given, else the one this chart creates. */}}
{{- define "osmo.tlsSecretName" -}}
{{- default (printf "%s-tls" (include "osmo.fullname" .)) .Values.tls.existingSecret -}}
{{- end -}}

{{- define "osmo.tlsClientSecretName" -}}
{{- default (printf "%s-tls-client" (include "osmo.fullname" .)) .Values.tls.client.existingSecret -}}
{{- end -}}

{{- define "osmo.authSecretName" -}}
{{- default (printf "%s-auth" (include "osmo.fullname" .)) .Values.auth.existingSecret -}}
{{- end -}}

{{- define "osmo.tokensSecretName" -}}
{{- default (printf "%s-tokens" (include "osmo.fullname" .)) .Values.tokens.existingSecret -}}
{{- end -}}

{{/* Does a pool run task pods that fetch their own data (kind kubernetes without workClaim)?
"true" or "". With auth.enabled their osmo containers log in as auth.podUser. */}}
{{- define "osmo.podData" -}}
{{- range .Values.pools -}}
{{- if and (eq (toString .kind) "kubernetes") (not (default dict .kubernetes).workClaim) -}}true{{- end -}}
{{- end -}}
{{- end -}}

{{/* Does zenoh authenticate every peer (user/password or mutual TLS)? "true" or "". Without
     it the server's network listener needs --insecure (API tokens still guard each request). */}}
{{- define "osmo.zenohAuthenticates" -}}
{{- if or .Values.auth.enabled (and .Values.tls.enabled .Values.tls.mtls) -}}true{{- end -}}
{{- end -}}

{{/* Is a zenoh config needed at all (TLS or user/password)? "true" or "". */}}
{{- define "osmo.zenohConfigured" -}}
{{- if or .Values.tls.enabled .Values.auth.enabled -}}true{{- end -}}
{{- end -}}

{{/* Where a client (worker, probe, server joining a router) reads its zenoh config. */}}
{{- define "osmo.clientConfigPath" -}}
{{- if .Values.auth.enabled -}}/run/osmo/zenoh/client.json5{{- else -}}/etc/osmo/zenoh/client.json5{{- end -}}
{{- end -}}

{{/* The endpoint workers and the server (router mode) dial: the Service, over TLS when enabled. */}}
{{- define "osmo.connectEndpoint" -}}
{{- if .Values.tls.enabled -}}
{{- printf "tls/%s:%d" (include "osmo.fullname" .) (int .Values.service.tlsPort) -}}
{{- else -}}
{{- printf "tcp/%s:%d" (include "osmo.fullname" .) (int .Values.service.port) -}}
{{- end -}}
{{- end -}}

{{/* Endpoints a listener (server, or router when enabled) binds, as a JSON list. */}}
{{- define "osmo.listenEndpoints" -}}
{{- $eps := list -}}
{{- if .Values.server.plainTcp -}}
{{- $eps = append $eps (printf "tcp/0.0.0.0:%d" (int .Values.service.port)) -}}
{{- else -}}
{{- $eps = append $eps (printf "tcp/127.0.0.1:%d" (int .Values.service.port)) -}}
{{- end -}}
{{- if .Values.tls.enabled -}}
{{- $eps = append $eps (printf "tls/0.0.0.0:%d" (int .Values.service.tlsPort)) -}}
{{- end -}}
{{- toJson $eps -}}
{{- end -}}

{{/* zenoh settings of a listener: certificates to present, clients to check. JSON object. */}}
{{- define "osmo.zenohListenerTransport" -}}
{{- $t := dict -}}
{{- if .Values.tls.enabled -}}
{{- $tls := dict "listen_certificate" "/etc/osmo/tls/server/tls.crt" "listen_private_key" "/etc/osmo/tls/server/tls.key" -}}
{{- if .Values.tls.mtls -}}
{{- $_ := set $tls "root_ca_certificate" "/etc/osmo/tls/server/ca.crt" -}}
{{- $_ := set $tls "enable_mtls" true -}}
{{- end -}}
{{- $_ := set $t "link" (dict "tls" $tls) -}}
{{- end -}}
{{- if .Values.auth.enabled -}}
{{- $_ := set $t "auth" (dict "usrpwd" (dict "dictionary_file" "/etc/osmo/auth/dictionary")) -}}
{{- end -}}
{{- toJson $t -}}
{{- end -}}

{{/* zenoh settings of a client: the CA to trust, the certificate to present (mtls). The
user/password are filled in at pod start from the auth Secret (see render-client-config.py). */}}
{{- define "osmo.zenohClientTransport" -}}
{{- $t := dict -}}
{{- if .Values.tls.enabled -}}
{{- $tls := dict "root_ca_certificate" "/etc/osmo/tls/server/ca.crt" -}}
{{- if .Values.tls.mtls -}}
{{- $_ := set $tls "connect_certificate" "/etc/osmo/tls/client/tls.crt" -}}
{{- $_ := set $tls "connect_private_key" "/etc/osmo/tls/client/tls.key" -}}
{{- $_ := set $tls "enable_mtls" true -}}
{{- end -}}
{{- $_ := set $t "link" (dict "tls" $tls) -}}
{{- end -}}
{{- toJson $t -}}
{{- end -}}

{{/* Volumes carrying the zenoh config and the Secrets it points at. */}}
{{/* The pod volumes of the zenoh config, TLS and auth Secrets. Args: root, authKeys (the auth
Secret's keys the pod may read; empty: all, the server's). A worker gets only its own user's
(and, for a data-mode kubernetes pool, the pods' user's): never the server's password or the
router's dictionary, which would let a compromised worker log in as the server. */}}
{{- define "osmo.securityVolumes" -}}
{{- $keys := .authKeys -}}
{{- with .root -}}
{{- if include "osmo.zenohConfigured" . }}
- name: zenoh-config
  configMap:
    name: {{ include "osmo.fullname" . }}-zenoh
{{- end }}
{{- if .Values.tls.enabled }}
- name: tls-server
  secret:
    secretName: {{ include "osmo.tlsSecretName" . }}
    defaultMode: 0440
{{- if .Values.tls.mtls }}
- name: tls-client
  secret:
    secretName: {{ include "osmo.tlsClientSecretName" . }}
    defaultMode: 0440
{{- end }}
{{- end }}
{{- if .Values.auth.enabled }}
- name: auth
  secret:
    secretName: {{ include "osmo.authSecretName" . }}
    defaultMode: 0440
    {{- with $keys }}
    items:
      {{- range . }}
      - key: {{ . }}
        path: {{ . }}
      {{- end }}
    {{- end }}
- name: zenoh-client-config
  emptyDir:
    medium: Memory
    sizeLimit: 1Mi
{{- end }}
{{- end -}}
{{- end -}}

{{- define "osmo.securityVolumeMounts" -}}
{{- if include "osmo.zenohConfigured" . }}
- name: zenoh-config
  mountPath: /etc/osmo/zenoh
  readOnly: true
{{- end }}
{{- if .Values.tls.enabled }}
- name: tls-server
  mountPath: /etc/osmo/tls/server
  readOnly: true
{{- if .Values.tls.mtls }}
- name: tls-client
  mountPath: /etc/osmo/tls/client
  readOnly: true
{{- end }}
{{- end }}
{{- if .Values.auth.enabled }}
- name: auth
  mountPath: /etc/osmo/auth
  readOnly: true
- name: zenoh-client-config
  mountPath: /run/osmo/zenoh
{{- end }}
{{- end -}}

{{/* With user/password auth, an init container writes the client config with the credentials
from the Secret into a memory-backed volume, so the password never sits in a ConfigMap. Args:
root, image, pullPolicy, server (true: the server's own user, which the router's access
control lets use the server's keys), pods (true: also pod.json5, with auth.podUser, which the
worker hands its task pods' data containers). */}}
{{- define "osmo.clientConfigInitContainer" -}}
{{- if .root.Values.auth.enabled }}
- name: zenoh-client-config
  image: {{ .image | quote }}
  imagePullPolicy: {{ .pullPolicy }}
  command:
    - python
    - /etc/osmo/zenoh/render-client-config.py
    - /etc/osmo/zenoh/client.json5
    {{- if .server }}
    - /etc/osmo/auth/server-user
    - /etc/osmo/auth/server-password
    {{- else }}
    - /etc/osmo/auth/user
    - /etc/osmo/auth/password
    {{- end }}
    - /run/osmo/zenoh/client.json5
    {{- if .pods }}
    - /etc/osmo/auth/pod-user
    - /etc/osmo/auth/pod-password
    - /run/osmo/zenoh/pod.json5
    {{- end }}
  securityContext:
    {{- toYaml .root.Values.containerSecurityContext | nindent 4 }}
  resources:
    requests:
      cpu: 10m
      memory: 32Mi
    limits:
      memory: 64Mi
  volumeMounts:
    {{- include "osmo.securityVolumeMounts" .root | nindent 4 }}
{{- end }}
{{- end -}}

{{/* A probe running a command, with timings from values. Args: cmd (list), timing (dict). */}}
{{- define "osmo.execProbe" -}}
exec:
  command:
    {{- toYaml .cmd | nindent 4 }}
{{ toYaml .timing }}
{{- end -}}

{{/* Kubernetes CPU quantity ("500m", "2", 1.5) as the plain number `--cpus` takes. */}}
{{- define "osmo.cpuNumber" -}}
{{- $s := toString . -}}
{{- if hasSuffix "m" $s -}}
{{- divf (trimSuffix "m" $s | float64) 1000 -}}
{{- else -}}
{{- include "osmo.quantityString" . -}}
{{- end -}}
{{- end -}}

{{/* A quantity as text: strings as written, whole numbers without an exponent (8589934592,
not 8.589934592e+09), other numbers as they print. */}}
{{- define "osmo.quantityString" -}}
{{- if kindIs "string" . -}}
{{- . -}}
{{- else if eq (float64 .) (floor .) -}}
{{- printf "%d" (int64 .) -}}
{{- else -}}
{{- toString . -}}
{{- end -}}
{{- end -}}

{{/* The router's access control, an allow-list with default deny: every peer but the server
(auth.user) may use only what osmo.transport.wire PEER_ALLOW lists (minus PEER_DENY), under the
cluster prefix osmo/local/; the server (auth.serverUser) may use the whole prefix. zenoh
matches a subject by its authenticated user name; the dictionary holds only auth.user and
auth.serverUser (and auth.podUser, with data-mode pods: it may only query podio/** and hear
the replies). This is the second wall: every message is also sealed end to end
(osmo.transport.seal). */}}
{{- define "osmo.routerAccessControl" -}}
{{- $p := "osmo/local/" -}}
{{- $all := list "put" "delete" "declare_subscriber" "query" "reply" "declare_queryable" "liveliness_token" "declare_liveliness_subscriber" "liveliness_query" -}}
{{- $allow := list
  (list "query" (list "api/*" "blob/server/*" "podio/**"))
  (list "declare_queryable" (list "blob/*/*" "podio/**"))
  (list "reply" (list "blob/*/*" "podio/**"))
  (list "declare_subscriber" (list "to-worker/*" "events/*" "stream/*/*"))
  (list "put" (list "stream/*/*"))
  (list "liveliness_token" (list "alive/worker/*"))
  (list "declare_liveliness_subscriber" (list "alive/**"))
  (list "liveliness_query" (list "alive/**")) -}}
{{- $deny := list (list "declare_queryable" (list "blob/server/*")) -}}
{{- $rules := list (dict "id" "osmo-egress" "messages" $all "flows" (list "egress") "permission" "allow" "key_exprs" (list (printf "%s**" $p))) -}}
{{- $rules = append $rules (dict "id" "osmo-server-all" "messages" $all "flows" (list "ingress") "permission" "allow" "key_exprs" (list (printf "%s**" $p))) -}}
{{- $peer := list "osmo-egress" -}}
{{- range $allow -}}
{{- $keys := list -}}
{{- range index . 1 }}{{ $keys = append $keys (printf "%s%s" $p .) }}{{ end -}}
{{- $id := printf "osmo-allow-%s" (index . 0) -}}
{{- $rules = append $rules (dict "id" $id "messages" (list (index . 0)) "flows" (list "ingress") "permission" "allow" "key_exprs" $keys) -}}
{{- $peer = append $peer $id -}}
{{- end -}}
{{- range $deny -}}
{{- $keys := list -}}
{{- range index . 1 }}{{ $keys = append $keys (printf "%s%s" $p .) }}{{ end -}}
{{- $id := printf "osmo-deny-%s" (index . 0) -}}
{{- $rules = append $rules (dict "id" $id "messages" (list (index . 0)) "flows" (list "ingress") "permission" "deny" "key_exprs" $keys) -}}
{{- $peer = append $peer $id -}}
{{- end -}}
{{- $subjects := list (dict "id" "osmo-peers" "usernames" (list .Values.auth.user)) (dict "id" "osmo-server" "usernames" (list .Values.auth.serverUser)) -}}
{{- $policies := list (dict "id" "osmo-peers" "subjects" (list "osmo-peers") "rules" $peer) (dict "id" "osmo-server" "subjects" (list "osmo-server") "rules" (list "osmo-egress" "osmo-server-all")) -}}
{{- if include "osmo.podData" . -}}
{{- /* the data containers of task pods: ask a worker's pod-data API, hear its answers */ -}}
{{- $podio := list (printf "%spodio/**" $p) -}}
{{- $rules = append $rules (dict "id" "osmo-pod-query" "messages" (list "query") "flows" (list "ingress") "permission" "allow" "key_exprs" $podio) -}}
{{- $rules = append $rules (dict "id" "osmo-pod-reply" "messages" (list "reply") "flows" (list "egress") "permission" "allow" "key_exprs" $podio) -}}
{{- $subjects = append $subjects (dict "id" "osmo-pods" "usernames" (list .Values.auth.podUser)) -}}
{{- $policies = append $policies (dict "id" "osmo-pods" "subjects" (list "osmo-pods") "rules" (list "osmo-pod-query" "osmo-pod-reply")) -}}
{{- end -}}
{{- dict "enabled" true "default_permission" "deny" "rules" $rules "subjects" $subjects "policies" $policies | toJson -}}
{{- end -}}

{{/*
The worker's --store-limit: worker.storeLimit, else half of worker.workdirSizeLimit (the kubelet
evicts a pod whose emptyDir passes its limit, so the store must stay well below it), else none
(the worker's own default: a quarter of its disk).
*/}}
{{- define "osmo.workerStoreLimit" -}}
{{- $w := .Values.worker -}}
{{- if $w.storeLimit -}}
{{- $w.storeLimit -}}
{{- else if $w.workdirSizeLimit -}}
{{- $n := regexFind "^[0-9]+$" (regexReplaceAll "[A-Za-z]+$" $w.workdirSizeLimit "") -}}
{{- $unit := regexFind "[A-Za-z]+$" $w.workdirSizeLimit -}}
{{- $factor := get (dict "" 1 "k" 1000 "M" 1000000 "G" 1000000000 "T" 1000000000000 "Ki" 1024 "Mi" 1048576 "Gi" 1073741824 "Ti" 1099511627776) $unit -}}
{{- if and $n $factor -}}
{{- div (mul (atoi $n) $factor) 2 -}}
{{- end -}}
{{- end -}}
{{- end }}

{{/*
Pods that run tasks (every pool's workers; the server with server.localPool) run them in
bubblewrap with `--sandbox <sandbox.mode>`; unless that mode is "off", they also get what
bubblewrap needs in a pod (README.md, "Sandboxed tasks"): their own user namespace
(sandbox.hostUsers), and each key of sandbox.podSecurityContext and
sandbox.containerSecurityContext in place of the same key of the base contexts. Every other pod
keeps the base contexts. Args of each: root, tasks (true: the pod runs tasks).
*/}}
{{- define "osmo.sandboxed" -}}
{{- if and .tasks (ne .root.Values.sandbox.mode "off") -}}true{{- end -}}
{{- end -}}

{{- define "osmo.podSecurityContext" -}}
{{- $context := deepCopy .root.Values.podSecurityContext -}}
{{- if include "osmo.sandboxed" . -}}
{{- range $key, $value := .root.Values.sandbox.podSecurityContext }}{{ $_ := set $context $key $value }}{{ end -}}
{{- end -}}
{{- toYaml $context -}}
{{- end -}}

{{- define "osmo.containerSecurityContext" -}}
{{- $context := deepCopy .root.Values.containerSecurityContext -}}
{{- if include "osmo.sandboxed" . -}}
{{- range $key, $value := .root.Values.sandbox.containerSecurityContext }}{{ $_ := set $context $key $value }}{{ end -}}
{{- end -}}
{{- toYaml $context -}}
{{- end -}}

{{/* spec.hostUsers of a pod (a line, or nothing). Args: root, tasks. */}}
{{- define "osmo.hostUsers" -}}
{{- if and (include "osmo.sandboxed" .) (not .root.Values.sandbox.hostUsers) -}}
hostUsers: false
{{- end -}}
{{- end -}}
