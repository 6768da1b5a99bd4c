#!/bin/sh
# Entry point of the farm's image: one role per container (xmpp | master | agent), configured by
# environment variables (see docker-compose.yml). Anything else runs `quekaro "$@"`.
set -eu
domain=${QUEKARO_XMPP_DOMAIN:-xmpp}
server=${QUEKARO_XMPP_SERVER:-$domain}
port=${QUEKARO_XMPP_PORT:-5222}
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
    exec prosody --config "$here/prosody/prosody.cfg.lua" -F
    ;;
master)
    # TLS on the data plane and verification of Prosody's certificate when the farm's CA is given.
    [ -n "${QUEKARO_TLS_CERT:-}" ] && set -- --tls-cert "$QUEKARO_TLS_CERT" --tls-key "$QUEKARO_TLS_KEY" "$@"
    [ -n "${QUEKARO_CA_FILE:-}" ] && set -- --ca-file "$QUEKARO_CA_FILE" "$@"
    exec quekaro master --home "${QUEKARO_HOME:-$HOME/farm}" --jid "master@$domain" --server "$server" \
        --port "$port" --register --http-host "${QUEKARO_HTTP_HOST:-0.0.0.0}" \
        --http-port "${QUEKARO_HTTP_PORT:-8765}" \
        --public-url "${QUEKARO_PUBLIC_URL:-http://master:8765}" "$@"
    ;;
agent)
    # Every replica gets its own JID (its container's host name) and registers it in-band: Prosody
    # allows that only from the compose network (QUEKARO_REGISTRATION_ALLOWLIST on the xmpp service).
    [ -n "${QUEKARO_CA_FILE:-}" ] && set -- --ca-file "$QUEKARO_CA_FILE" "$@"
    exec quekaro agent --server "$server" --port "$port" --jid "agent-${QUEKARO_AGENT_NAME:-$(hostname)}@$domain" \
        --master "master@$domain" --master-url "${QUEKARO_PUBLIC_URL:-http://master:8765}" \
        --register --threads "${QUEKARO_THREADS:-2}" --workdir "$HOME/agent" "$@"
    ;;
health)
    # A container's healthcheck: `health xmpp` (the client port accepts) or `health master` (the HTTP
    # API answers /healthz), on the ports the role was given.
    case "${1:-}" in
    xmpp) exec python3 -c "import socket,sys; socket.create_connection(('127.0.0.1', int(sys.argv[1])), 3)" "$port" ;;
    master) exec python3 -c "import urllib.request,sys; urllib.request.urlopen(sys.argv[1], timeout=3)" \
        "http://127.0.0.1:${QUEKARO_HTTP_PORT:-8765}/healthz" ;;
    *) echo "health: xmpp or master" >&2; exit 2 ;;
    esac
    ;;
*)
    exec quekaro "$role" "$@"
    ;;
esac
