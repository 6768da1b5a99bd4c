-- Prosody 0.12 for a QUEKARO farm spread over several hosts.
--
-- One VirtualHost = the JID domain of the master and the render agents. Registration is closed:
-- accounts are created by deploy/prosody/make-accounts.sh (prosodyctl register). Client connections
-- must use TLS (STARTTLS) with the certificate named below. No server-to-server links, no HTTP.
--
-- Every site-specific value comes from the environment, so the same file serves a Docker service,
-- a host install and the tests (core.xmpp_server.ProsodyServer runs it on 127.0.0.1):
--   QUEKARO_XMPP_DOMAIN      JID domain, also the name clients connect to      (default "xmpp")
--   QUEKARO_XMPP_PORT        client port                                        (default 5222)
--   QUEKARO_XMPP_INTERFACE   address to listen on                               (default "*")
--   QUEKARO_XMPP_CERT/KEY    PEM certificate and key for the domain  (default /etc/prosody/certs/<domain>.crt/.key)
--   QUEKARO_PROSODY_DATA     data directory (accounts)                          (default /var/lib/prosody)
--   QUEKARO_PROSODY_PIDFILE  pid file                                           (default /run/prosody/prosody.pid)
--   QUEKARO_PROSODY_LOG      log file, or "console"                             (default "console")
--   QUEKARO_PROSODY_USER     user to run as when started as root                (default "prosody")
--   QUEKARO_XMPP_STANZA_LIMIT  largest stanza accepted, bytes                   (default 262144)
--   QUEKARO_XMPP_C2S_RATE    what a client may send per second, "N kb/s" (1 kb = 1000 bytes)  (default "32kb/s")
--   QUEKARO_XMPP_UNLIMITED   comma-separated JIDs exempt from that rate        (default master@<domain>)
-- (an empty variable counts as unset)

local function env(name)
	local value = os.getenv(name)
	if value == "" then return nil end
	return value
end
local domain = env("QUEKARO_XMPP_DOMAIN") or "xmpp"

-- Stanza size limit: 256 KiB (Prosody's default, stated here on purpose). A larger stanza makes
-- Prosody close the sender's stream, and SPADE raises nothing: the farm keeps XMPP bodies under
-- 64 KiB (core.xmpp.DEFAULT_MAX_BODY) and moves scenes and tiles over HTTP.
c2s_stanza_size_limit = tonumber(env("QUEKARO_XMPP_STANZA_LIMIT") or "262144")
-- Before a client has logged in, far less: a stream that sends more in one element is closed
-- (policy-violation) before Prosody keeps it. 10 kB is Prosody 0.12's default, stated here on purpose:
-- without a limit, 3 MB of unclosed tags from a stranger grew Prosody by hundreds of MB.
c2s_unauthed_stanza_size_limit = 10000

-- Prosody reads each client at QUEKARO_XMPP_C2S_RATE (mod_limits; 0.12's epoll backend paces a
-- connection from its first byte, with no burst): a peer that floods slows itself down before the master
-- has to parse what it sends (the master also refuses, unread, what an agent sends past a burst of 500
-- messages and then 250 a second: core.transport.rates). An agent's messages are small (a heartbeat every 2 s, bids, informs; its
-- largest, 64 bids, about 3 KB). The master calls every agent at once and is exempt: name it in
-- QUEKARO_XMPP_UNLIMITED if its JID is not master@<domain>.
local rate = env("QUEKARO_XMPP_C2S_RATE") or "32kb/s"
if not rate:match("^%d+ ?[kKmMgG]?[bB]/s$") then
	-- mod_limits would log one line and fall back to 3000 bytes a second
	error("QUEKARO_XMPP_C2S_RATE: " .. rate .. " is not a rate like 32kb/s")
end
limits = { c2s = { rate = rate; } }
local unlimited = {}
for jid in (env("QUEKARO_XMPP_UNLIMITED") or ("master@" .. domain)):gmatch("[^,%s]+") do
	unlimited[#unlimited + 1] = jid
end
unlimited_jids = unlimited

c2s_ports = { tonumber(env("QUEKARO_XMPP_PORT") or "5222") }
c2s_interfaces = { env("QUEKARO_XMPP_INTERFACE") or "*" }
c2s_direct_tls_ports = {}
s2s_ports = {}
http_ports = {}
https_ports = {}

data_path = env("QUEKARO_PROSODY_DATA") or "/var/lib/prosody"
umask = "077"  -- its accounts, pid and log for its user alone (mod_posix; Prosody's own default is 027)
pidfile = env("QUEKARO_PROSODY_PIDFILE") or "/run/prosody/prosody.pid"
-- (options set here cannot be read back in this file: keep values needed twice in locals)
local user = env("QUEKARO_PROSODY_USER") or "prosody"
prosody_user = user
prosody_group = user
run_as_root = (user == "root")

local log_to = env("QUEKARO_PROSODY_LOG") or "console"
-- Prosody's console sink is "*console"; a bare "console" would be a file of that name in the folder.
log = { info = (log_to == "console") and "*console" or log_to }

modules_enabled = {
	"roster";      -- SPADE asks for its roster at login
	"saslauth";
	"tls";
	"disco";
	"ping";        -- SPADE's keepalive (XEP-0199)
	"offline";     -- messages to an agent that is reconnecting wait for it
	"posix";       -- pid file
	"limits";      -- each client's send rate (above)
}
-- Registration is closed, always: only accounts made with prosodyctl exist (a local farm makes them,
-- the compose file's xmpp role makes them, make-accounts.sh makes them for several hosts).
modules_disabled = { "s2s"; "register"; "http"; "admin_shell" }
allow_registration = false

-- Clients must encrypt; passwords are stored hashed.
c2s_require_encryption = true
s2s_require_encryption = true
authentication = "internal_hashed"
storage = "internal"

local cert = env("QUEKARO_XMPP_CERT") or ("/etc/prosody/certs/" .. domain .. ".crt")
local key = env("QUEKARO_XMPP_KEY") or ("/etc/prosody/certs/" .. domain .. ".key")
certificates = cert:match("^(.*)/[^/]*$") or "certs"

VirtualHost(domain)
	ssl = { certificate = cert; key = key; }
