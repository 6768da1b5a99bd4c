#!/bin/sh
# Entry point of the farm's image: one role per container (xmpp | master | agent), configured by
# environment variables (see docker-compose.yml). Anything else runs `quekaro "$@"`.
set -eu
domain=${QUEKARO_XMPP_DOMAIN:-xmpp}
server=${QUEKARO_XMPP_SERVER:-$domain}
port=${QUEKARO_XMPP_PORT:-5222}
# The farm's XMPP passwords, one file each (made by the xmpp role), and the agents' claims on them: a
# volume only the farm's containers mount.
secrets=${QUEKARO_SECRETS_DIR:-$HOME/secrets}
here=$(cd "$(dirname "$0")" && pwd)
role=${1:-}
[ $# -gt 0 ] && shift

case "$role" in
ca)
    # The farm's CA and the servers' certificates, made once into QUEKARO_CA_DIR (a shared volume).
    dir=${QUEKARO_CA_DIR:-$HOME/ca}
    [ -f "$dir/ca.pem" ] || quekaro ca init --dir "$dir"
    [ -f "$dir/xmpp.pem" ] || quekaro ca issue xmpp "$domain" --dir "$dir"
    [ -f "$dir/master.pem" ] || quekaro ca issue master ${QUEKARO_MASTER_HOSTS:-master 127.0.0.1 localhost} --dir "$dir"
    ;;
xmpp)
    data=${QUEKARO_PROSODY_DATA:-$HOME/prosody}
    mkdir -p "$data/data" "$data/certs"
    cert=${QUEKARO_XMPP_CERT:-$data/certs/$domain.crt}; key=${QUEKARO_XMPP_KEY:-$data/certs/$domain.key}
    if [ ! -f "$cert" ]; then
        openssl req -x509 -newkey rsa:2048 -nodes -days 3650 -subj "/CN=$domain" \
            -addext "subjectAltName=DNS:$domain" -keyout "$key" -out "$cert" 2>/dev/null
    fi
    export QUEKARO_XMPP_DOMAIN="$domain" QUEKARO_XMPP_CERT="$cert" QUEKARO_XMPP_KEY="$key" \
           QUEKARO_PROSODY_DATA="$data/data" QUEKARO_PROSODY_PIDFILE="$data/prosody.pid" \
           QUEKARO_PROSODY_LOG=console QUEKARO_PROSODY_USER="$(id -un)"
    # Registration is closed: every account is made here, before Prosody listens (and so before the
    # master and the agents, which wait for it): master and a pool agent-1 .. agent-N, each with its own
    # random password in $secrets. A restart keeps the passwords (a running master or agent logs in
    # again) and makes the accounts again with them, so accounts and files agree even if one volume was
    # lost; a smaller N removes the surplus accounts.
    sh "$here/prosody/make-accounts.sh" --dir "$secrets" "$domain" "${QUEKARO_AGENT_SLOTS:-16}"
    (umask 077 && mkdir -p "$secrets/claims")
    exec prosody --config "$here/prosody/prosody.cfg.lua" -F
    ;;
master)
    # TLS on the data plane and verification of Prosody's certificate when the farm's CA is given.
    [ -n "${QUEKARO_TLS_CERT:-}" ] && set -- --tls-cert "$QUEKARO_TLS_CERT" --tls-key "$QUEKARO_TLS_KEY" "$@"
    [ -n "${QUEKARO_CA_FILE:-}" ] && set -- --ca-file "$QUEKARO_CA_FILE" "$@"
    exec quekaro master --home "${QUEKARO_HOME:-$HOME/farm}" --jid "master@$domain" --server "$server" \
        --port "$port" --password-file "$secrets/master.password" --http-host "${QUEKARO_HTTP_HOST:-0.0.0.0}" \
        --http-port "${QUEKARO_HTTP_PORT:-8765}" \
        --public-url "${QUEKARO_PUBLIC_URL:-http://master:8765}" "$@"
    ;;
agent)
    # Every replica logs in as one account of the xmpp role's pool, claimed here: claims/agent-I is
    # locked (flock) by this process, whose lock the agent inherits through exec, so a claim lasts exactly
    # as long as its agent, however it ends (the kernel drops the lock of a killed or crashed process):
    # no stale claim is left to clear, and the xmpp role never clears them. The file names the holder
    # (QUEKARO_AGENT_NAME, by default the host name: a container's id); a restarted container takes
    # its own account back when it is free, so its agent keeps its name.
    me=${QUEKARO_AGENT_NAME:-$(hostname)}
    umask 077
    mkdir -p "$secrets/claims"
    take() {  # account: hold its claim on fd 9, or fail
        exec 9>>"$secrets/claims/$1"
        flock -n 9 || return 1
        printf '%s\n' "$me" > "$secrets/claims/$1"
    }
    account=
    n=0
    while [ -f "$secrets/agent-$((n + 1)).password" ]; do n=$((n + 1)); done
    [ "$n" -gt 0 ] || { echo "agent: no XMPP account in $secrets/ (the xmpp service makes them there)" >&2; exit 1; }
    i=1
    while [ "$i" -le "$n" ] && [ -z "$account" ]; do  # its own account first
        [ "$(cat "$secrets/claims/agent-$i" 2>/dev/null)" = "$me" ] && take "agent-$i" && account=agent-$i
        i=$((i + 1))
    done
    i=1
    while [ "$i" -le "$n" ] && [ -z "$account" ]; do
        take "agent-$i" && account=agent-$i
        i=$((i + 1))
    done
    if [ -z "$account" ]; then
        echo "agent: all $n XMPP accounts (agent-1..agent-$n@$domain) are taken: set QUEKARO_AGENT_SLOTS on the xmpp service to run more agents" >&2
        exit 1
    fi
    echo "agent: $me logs in as $account@$domain"
    [ -n "${QUEKARO_CA_FILE:-}" ] && set -- --ca-file "$QUEKARO_CA_FILE" "$@"
    exec quekaro agent --server "$server" --port "$port" --jid "$account@$domain" \
        --password-file "$secrets/$account.password" \
        --master "master@$domain" --master-url "${QUEKARO_PUBLIC_URL:-http://master:8765}" \
        --threads "${QUEKARO_THREADS:-2}" --workdir "$HOME/agent" "$@"
    ;;
health)
    # A container's healthcheck: `health xmpp` (the client port accepts) or `health master` (the HTTP
    # API answers /healthz), on the ports the role was given; HTTPS where the master has a certificate
    # (QUEKARO_TLS_CERT), verified against QUEKARO_CA_FILE.
    case "${1:-}" in
    xmpp) exec python3 -c "import socket,sys; socket.create_connection(('127.0.0.1', int(sys.argv[1])), 3)" "$port" ;;
    master)
        scheme=http; [ -n "${QUEKARO_TLS_CERT:-}" ] && scheme=https
        exec python3 -c "import ssl,sys,urllib.request; tls = ssl.create_default_context(cafile=sys.argv[2] or None) \
if sys.argv[1].startswith('https:') else None; urllib.request.urlopen(sys.argv[1], timeout=3, context=tls)" \
            "$scheme://127.0.0.1:${QUEKARO_HTTP_PORT:-8765}/healthz" "${QUEKARO_CA_FILE:-}" ;;
    *) echo "health: xmpp or master" >&2; exit 2 ;;
    esac
    ;;
*)
    exec quekaro "$role" "$@"
    ;;
esac
