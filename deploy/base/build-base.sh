#!/usr/bin/env bash
# Builds a minimal base image for the nephele image without any registry: a root file system
# holding only what the nephele binary links against (its shared libraries and the dynamic
# loader, found with ldd), an /etc/passwd and /etc/group naming the unprivileged user 10001
# and a world-writable /tmp, imported with `docker import`.
#
# On a machine that can pull images you do not need this: deploy/Dockerfile builds on
# debian:bookworm-slim by default. Here (no registry) the tests run
#   deploy/base/build-base.sh target/release/nephele nephele-base:local
#   docker build -f deploy/Dockerfile --build-arg BASE=nephele-base:local -t nephele:local .
#
# Usage: build-base.sh NEPHELE_BINARY [TAG]   (TAG defaults to nephele-base:local)
set -euo pipefail

binary=${1:?usage: build-base.sh NEPHELE_BINARY [TAG]}
tag=${2:-nephele-base:local}
[ -x "$binary" ] || { echo "build-base.sh: $binary is not an executable" >&2; exit 2; }
command -v docker >/dev/null || { echo "build-base.sh: docker is not installed" >&2; exit 2; }

root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT

# Every shared library the binary needs, and the loader, at the paths the binary expects.
libs=$(ldd "$binary" | awk '/=> \//{print $3} /^[[:space:]]*\/[^ ]+ \(/{print $1}')
[ -n "$libs" ] || { echo "build-base.sh: ldd found no libraries in $binary (a static binary needs no base: use FROM scratch)" >&2; exit 2; }
for lib in $libs; do
    mkdir -p "$root$(dirname "$lib")"
    cp -L "$lib" "$root$lib"
done
# glibc's own resolver modules are in libc since 2.34; nsswitch says to use files then DNS.
mkdir -p "$root/etc" "$root/tmp" "$root/usr/local/bin" "$root/var/lib/nephele"
chmod 1777 "$root/tmp"
printf 'root:x:0:0:root:/root:/sbin/nologin\nnephele:x:10001:10001:nephele:/var/lib/nephele:/sbin/nologin\n' >"$root/etc/passwd"
printf 'root:x:0:\nnephele:x:10001:\n' >"$root/etc/group"
printf 'passwd: files\ngroup: files\nhosts: files dns\n' >"$root/etc/nsswitch.conf"

tar -C "$root" --numeric-owner -c . | docker import \
    --message "nephele base: $(basename "$binary")'s shared libraries from $(uname -srm)" - "$tag" >/dev/null
echo "built $tag ($(du -sh "$root" | cut -f1) of libraries and loader)"
