#!/bin/sh
# Create the farm's XMPP accounts on Prosody (registration is closed, so this is the only way in):
# master@DOMAIN and agent-1@DOMAIN .. agent-N@DOMAIN, with `prosodyctl register`.
#
# usage: make-accounts.sh DOMAIN N [PASSWORD_FILE]
#   Passwords come from the environment when set (QUEKARO_MASTER_PASSWORD, QUEKARO_AGENT_PASSWORD for
#   every agent), otherwise each account gets a random one. Either way they are written, one
#   "jid password" line per account, to PASSWORD_FILE (default ./xmpp-passwords.txt, mode 600):
#   hand each process its own line only.
# usage: make-accounts.sh --dir DIR DOMAIN N
#   One file per account, DIR/master.password and DIR/agent-I.password (DIR 700, files 600), each with
#   its own random password (the environment's are not used). Safe to run at every start of the server
#   (the compose file's xmpp role does): a password already in DIR is kept and its account made again
#   with it, so the accounts match the files whichever of the two survived, and a running master or agent
#   logs in again after the server restarts; the accounts agent-I with I > N and their files are removed.
#
#   PROSODY_CONFIG selects the config (default: the prosody.cfg.lua next to this script); its
#   QUEKARO_* variables (data directory, domain...) must match the running server's.
set -eu

usage() { echo "usage: $0 DOMAIN N [PASSWORD_FILE] | $0 --dir DIR DOMAIN N" >&2; exit 2; }
dir=
if [ "${1:-}" = --dir ]; then
    [ $# -eq 4 ] || usage
    dir=$2
    shift 2
fi
[ $# -ge 2 ] || usage
domain=$1
count=$2
out=${3:-./xmpp-passwords.txt}
case $count in ''|*[!0-9]*) echo "N must be a number, got '$count'" >&2; exit 2 ;; esac
here=$(cd "$(dirname "$0")" && pwd)
config=${PROSODY_CONFIG:-$here/prosody.cfg.lua}
export QUEKARO_XMPP_DOMAIN="${QUEKARO_XMPP_DOMAIN:-$domain}"
command -v prosodyctl >/dev/null || { echo "prosodyctl not found (Debian package prosody)" >&2; exit 1; }

# base64 without '/+=': never starts with '-', so prosodyctl cannot take it for an option
random_password() { openssl rand -base64 18 | tr -d '/+=\n'; }

umask 077
make_account() {  # user password
    # prosodyctl says why it failed on stdout (a data folder the Prosody user cannot write, say): shown
    said=$(prosodyctl --config "$config" register "$1" "$domain" "$2" 2>&1) || {
        printf 'prosodyctl register %s@%s failed:\n%s\n' "$1" "$domain" "$said" >&2; exit 1; }
}

if [ -n "$dir" ]; then
    mkdir -p "$dir"
    chmod 700 "$dir"
    account() {  # user: its password file kept (or made, written before the account so none is lost)
        file=$dir/$1.password
        if [ -s "$file" ]; then
            password=$(cat "$file")
        else
            password=$(random_password)
            printf '%s\n' "$password" > "$dir/.$1.tmp"
            mv "$dir/.$1.tmp" "$file"
        fi
        chmod 600 "$file"
        make_account "$1" "$password"
    }
    account master
    i=1
    while [ "$i" -le "$count" ]; do
        account "agent-$i"
        i=$((i + 1))
    done
    for file in "$dir"/agent-*.password; do  # a pool made larger before: its surplus goes
        [ -e "$file" ] || continue
        user=${file##*/}; user=${user%.password}
        case ${user#agent-} in ''|*[!0-9]*) continue ;; esac
        [ "${user#agent-}" -gt "$count" ] || continue
        prosodyctl --config "$config" deluser "$user@$domain" >/dev/null 2>&1 || true  # (gone already)
        rm -f "$file"
    done
    echo "accounts master and agent-1..agent-$count on $domain; passwords in $dir"
    exit 0
fi

: > "$out"
register() {  # user password
    make_account "$1" "$2"
    printf '%s@%s %s\n' "$1" "$domain" "$2" >> "$out"
}

register master "${QUEKARO_MASTER_PASSWORD:-$(random_password)}"
i=1
while [ "$i" -le "$count" ]; do
    register "agent-$i" "${QUEKARO_AGENT_PASSWORD:-$(random_password)}"
    i=$((i + 1))
done
echo "created master and $count agents on $domain; passwords in $out"
