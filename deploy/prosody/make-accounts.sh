#!/bin/sh
# Create the farm's XMPP accounts on Prosody (registration is closed, so this is the only way in):
# master@DOMAIN and agent-1@DOMAIN .. agent-N@DOMAIN, with `prosodyctl register`.
#
# usage: make-accounts.sh DOMAIN N [PASSWORD_FILE]
#   Passwords come from the environment when set (QUEKARO_MASTER_PASSWORD, QUEKARO_AGENT_PASSWORD for
#   every agent), otherwise each account gets a random one. Either way they are written, one
#   "jid password" line per account, to PASSWORD_FILE (default ./xmpp-passwords.txt, mode 600):
#   hand each process its own line only.
#   PROSODY_CONFIG selects the config (default: the prosody.cfg.lua next to this script); its
#   QUEKARO_* variables (data directory, domain...) must match the running server's.
set -eu

usage() { echo "usage: $0 DOMAIN N [PASSWORD_FILE]" >&2; exit 2; }
[ $# -ge 2 ] || usage
domain=$1
count=$2
out=${3:-./xmpp-passwords.txt}
case $count in ''|*[!0-9]*) echo "N must be a number, got '$count'" >&2; exit 2 ;; esac
here=$(cd "$(dirname "$0")" && pwd)
config=${PROSODY_CONFIG:-$here/prosody.cfg.lua}
export QUEKARO_XMPP_DOMAIN="${QUEKARO_XMPP_DOMAIN:-$domain}"
command -v prosodyctl >/dev/null || { echo "prosodyctl not found (Debian package prosody)" >&2; exit 1; }

random_password() { openssl rand -base64 18 | tr -d '/+=\n'; }

umask 077
: > "$out"
register() {  # user password
    # prosodyctl says why it failed on stdout (a data folder the Prosody user cannot write, say): shown
    said=$(prosodyctl --config "$config" register "$1" "$domain" "$2" 2>&1) || {
        printf 'prosodyctl register %s@%s failed:\n%s\n' "$1" "$domain" "$said" >&2; exit 1; }
    printf '%s@%s %s\n' "$1" "$domain" "$2" >> "$out"
}

register master "${QUEKARO_MASTER_PASSWORD:-$(random_password)}"
i=1
while [ "$i" -le "$count" ]; do
    register "agent-$i" "${QUEKARO_AGENT_PASSWORD:-$(random_password)}"
    i=$((i + 1))
done
echo "created master and $count agents on $domain; passwords in $out"
