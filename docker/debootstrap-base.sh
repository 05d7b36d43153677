#!/usr/bin/env bash
# Builds a Debian base image from Debian's packages alone (debootstrap, then `docker import`), for
# machines that reach a Debian mirror but no container registry. It stands in for
# debian:SUITE-slim: the same release, slimmed the same way (no manuals, docs or locales, also for
# packages installed later), apt lists and package cache removed.
#
# Usage: bash docker/debootstrap-base.sh [IMAGE [SUITE]]
#   SUITE: the Debian release (default bookworm; trixie for the newest Python Debian ships, 3.13);
#   IMAGE: default esrp-base:SUITE.
# Environment: ESRP_DEBIAN_MIRROR (default: the host's apt mirror for Debian, else
# http://deb.debian.org/debian), ESRP_DEBIAN_SECURITY_MIRROR (likewise for debian-security).
# Needs root (debootstrap), debootstrap and a running Docker daemon. Takes about a minute.
set -euo pipefail

suite="${2:-bookworm}"
image="${1:-esrp-base:$suite}"

# The first URI of the host's apt sources (deb822 or one-line format) whose path ends in $1.
host_mirror() {
    cat /etc/apt/sources.list.d/*.sources /etc/apt/sources.list.d/*.list /etc/apt/sources.list 2>/dev/null \
        | grep -oE 'https?://[^ ]+' | grep -E "/$1/?\$" | head -n1 | sed 's:/$::' || true
}
mirror="${ESRP_DEBIAN_MIRROR:-$(host_mirror debian)}"
mirror="${mirror:-http://deb.debian.org/debian}"
security="${ESRP_DEBIAN_SECURITY_MIRROR:-$(host_mirror debian-security)}"
security="${security:-http://deb.debian.org/debian-security}"

if ! command -v debootstrap >/dev/null 2>&1; then
    echo "debootstrap is missing: apt-get install debootstrap" >&2
    exit 1
fi

root="$(mktemp -d /tmp/esrp-rootfs.XXXXXX)"
trap 'rm -rf "$root"' EXIT

echo "debootstrap --variant=minbase $suite from $mirror"
debootstrap --variant=minbase "$suite" "$root" "$mirror" >"$root.log" 2>&1 || {
    tail -n 30 "$root.log" >&2
    rm -f "$root.log"
    exit 1
}
rm -f "$root.log"

# Slim like the official -slim images: dpkg skips these paths from now on, and they go now.
cat >"$root/etc/dpkg/dpkg.cfg.d/docker-slim" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/groff/*
path-exclude /usr/share/info/*
path-exclude /usr/share/linda/*
path-exclude /usr/share/lintian/overrides/*
path-exclude /usr/share/locale/*
path-exclude /usr/share/man/*
EOF
find "$root/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
find "$root/usr/share/doc" -mindepth 1 -type d -empty -delete
rm -rf "$root"/usr/share/{groff,info,linda,lintian/overrides,locale,man}/*

# apt as in the official images: no package cache kept after an install.
cat >"$root/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
EOF
rm -f "$root/etc/apt/sources.list"
cat >"$root/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $mirror
Suites: $suite $suite-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: $security
Suites: $suite-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* "$root"/var/log/* "$root"/tmp/*
: >"$root/etc/machine-id"

tar --numeric-owner -C "$root" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD ["bash"]' \
    --message "debootstrap --variant=minbase $suite $mirror, slimmed (docker/debootstrap-base.sh)" \
    - "$image" >/dev/null
echo "$image: $(docker image inspect --format '{{.Size}}' "$image" | awk '{printf "%.0f MB", $1 / 1e6}')"
