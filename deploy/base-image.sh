#!/bin/sh
# The farm image's base, made without an image registry: a minimal Debian from Debian's packages
# (debootstrap), with this machine's CPython 3.11 copied into /usr/local, `docker import`ed and tagged.
# Skips when the tag exists.
#
#   sh deploy/base-image.sh [TAG]        TAG: quekaro-base:bookworm (the default of deploy/Dockerfile)
#
# Why not Debian's python3: bookworm's is 3.11.2, whose tarfile lacks the extraction filters (3.11.4) the
# farm's bundles use, and no other Debian release has 3.11. QUEKARO_BASE_PYTHON: the CPython 3.11 install
# to copy (its sys.base_prefix; default: that of `python3.11` on PATH), built for this Debian release
# (pyenv builds it so). QUEKARO_DEBIAN_MIRROR: the mirror (default http://deb.debian.org/debian).
# Needs root, docker and debootstrap. The suite is the tag's version.
set -eu
tag=${1:-quekaro-base:bookworm}
suite=${tag##*:}
mirror=${QUEKARO_DEBIAN_MIRROR:-http://deb.debian.org/debian}
# The Debian libraries CPython's own extension modules load (ssl, ctypes, sqlite3, lzma, bz2, zlib,
# readline, curses, dbm, xml), and the CA certificates.
libraries=ca-certificates,libssl3,libffi8,libsqlite3-0,liblzma5,libbz2-1.0,zlib1g,libreadline8,libncursesw6,libgdbm6,libexpat1

if docker image inspect "$tag" >/dev/null 2>&1; then
    echo "base-image: $tag exists"
    exit 0
fi
fail() { echo "base-image: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || fail "debootstrap needs root"
command -v debootstrap >/dev/null || fail "needs debootstrap (apt-get install debootstrap)"
python=${QUEKARO_BASE_PYTHON:-$(python3.11 -c 'import sys; print(sys.base_prefix)' 2>/dev/null || true)}
[ -x "$python/bin/python3.11" ] || fail "no CPython 3.11 install: give its prefix in QUEKARO_BASE_PYTHON"
"$python/bin/python3.11" -c 'import sys, tarfile; tarfile.data_filter; sys.exit(sys.version_info < (3, 11, 4))' \
    2>/dev/null || fail "$python/bin/python3.11 is older than 3.11.4 (no tarfile extraction filters)"

root=$(mktemp -d /var/tmp/quekaro-base.XXXXXX)
cleanup() {  # a failed debootstrap can leave /proc and /sys mounted inside: unmount before removing
    for m in $(awk -v r="$root/" 'index($2, r) == 1 {print $2}' /proc/mounts | sort -r); do umount -l "$m"; done
    rm -rf --one-file-system "$root" "$root.log"
}
trap cleanup EXIT INT TERM

echo "base-image: debootstrap $suite from $mirror, with the CPython of $python"
debootstrap --variant=minbase --include="$libraries" "$suite" "$root" "$mirror" > "$root.log" 2>&1 \
    || { tail -20 "$root.log" >&2; exit 1; }
# CPython into /usr/local, as python's own images have it: interpreter, shared library, standard library
# (without its tests, IDLE and Tk, and without the packages installed into it here).
mkdir -p "$root/usr/local/bin" "$root/usr/local/lib"
cp -a "$python/bin/python3.11" "$root/usr/local/bin/"
ln -s python3.11 "$root/usr/local/bin/python3"
ln -s python3.11 "$root/usr/local/bin/python"
cp -a "$python"/lib/libpython3.11.so* "$root/usr/local/lib/" 2>/dev/null || true  # a shared build's
tar -C "$python/lib" --exclude=python3.11/site-packages --exclude=python3.11/test --exclude=python3.11/idlelib \
    --exclude=python3.11/tkinter --exclude=python3.11/turtledemo --exclude='python3.11/config-*' -c python3.11 \
    | tar -C "$root/usr/local/lib" -x
mkdir -p "$root/usr/local/lib/python3.11/site-packages"
# The interpreter's RUNPATH names its old prefix: the loader's cache finds the library in /usr/local/lib.
chroot "$root" /sbin/ldconfig
chroot "$root" /usr/local/bin/python3 -c 'import ssl, ctypes, sqlite3, lzma, bz2, zlib, venv, ensurepip, tarfile
tarfile.data_filter' || fail "the copied CPython does not run in the $suite tree"
# As in Debian's own images: services never start at install time, the updates' suites are known, no caches.
printf '#!/bin/sh\nexit 101\n' > "$root/usr/sbin/policy-rc.d"
chmod 755 "$root/usr/sbin/policy-rc.d"
cat > "$root/etc/apt/sources.list" <<EOF
deb $mirror $suite main
deb $mirror $suite-updates main
deb http://deb.debian.org/debian-security $suite-security main
EOF
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/archives/*.deb "$root"/var/log/*.log
version=$("$python/bin/python3.11" -c 'import platform; print(platform.python_version())')
tar --numeric-owner -C "$root" -c . | docker import -c 'ENV LANG=C.UTF-8' -c 'CMD ["/usr/local/bin/python3"]' \
    -c "LABEL org.quekaro.python=$version org.quekaro.debian=$suite" -m "debootstrap $suite, CPython $version" - "$tag"
echo "base-image: $tag made (Debian $suite, CPython $version)"
