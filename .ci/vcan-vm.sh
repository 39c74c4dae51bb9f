#!/usr/bin/env bash
# Run a command on a real kernel vcan0: boot Debian's own kernel in a qemu VM (TCG) with virtme-ng.
#
#   bash .ci/vcan-vm.sh GUEST_COMMAND...
#   e.g. bash .ci/vcan-vm.sh "$TCF_HIL_PY" tests/vm/vcan_smoke.py
#
# The host kernel needs no CAN support and no KVM (nested KVM is unusable on our runners, so the
# VM always runs on TCG). Recipe: /work/shared/research/can-transports.md, section D.
#
# Inside the guest, as root, in the repository root:
#   modprobe vcan && modprobe can_raw && ip link add dev vcan0 type vcan && ip link set vcan0 up
#   && GUEST_COMMAND
# The guest sees the host filesystem read-only, so host tools and the host's Python (with its
# site-packages) work inside by their absolute paths. The only writable host directory is VM_OUT.
#
# Exported to the guest command:
#   VM_OUT       writable output directory, shared with the host (default: <repo>/.vm-out)
#   TCF_HIL_PY   absolute path of the host interpreter (default: the `python` on PATH)
#
# Exit status: the guest command's. If the VM cannot be prepared or does not start, prints one
# line "vcan-vm: SKIPPED: <why>" to stderr and exits 0.
#
# Environment:
#   TCF_HIL_SKIP_VM=1      skip the stage (prints the SKIPPED line)
#   TCF_HIL_VM_CACHE       cache for kmin/ (pruned kernel) and vng-venv/ (default ~/.cache/tcf-hil-vm)
#   TCF_HIL_VM_KERNEL      use this vmlinuz (with lib/modules/<kver>/ beside its boot/) instead
#   TCF_HIL_VM_OUT         output directory (emptied at the start of each run)
#   TCF_HIL_VM_TIMEOUT     wall-clock limit for boot + test + power-off in seconds (default 600)
#   TCF_HIL_PY             interpreter to export to the guest
set -euo pipefail

VNG_VERSION=1.42
APT_PKGS=(qemu-system-x86 kmod busybox-static udev can-utils iproute2)

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)
CACHE=${TCF_HIL_VM_CACHE:-$HOME/.cache/tcf-hil-vm}
OUT=${TCF_HIL_VM_OUT:-$REPO/.vm-out}
TIMEOUT=${TCF_HIL_VM_TIMEOUT:-600}

say() { echo "vcan-vm: $*" >&2; }
skip() { echo "vcan-vm: SKIPPED: $*" >&2; exit 0; }
now() { date +%s.%N; }
took() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f s", b - a }'; }

if [[ $# -eq 0 ]]; then
  echo "usage: bash .ci/vcan-vm.sh GUEST_COMMAND..." >&2
  exit 2
fi
if [[ "${TCF_HIL_SKIP_VM:-}" == 1 ]]; then
  skip "TCF_HIL_SKIP_VM=1 is set"
fi

T0=$(now)
# From here until the boot, any unexpected failure means "could not prepare": skip, never silently.
trap 'skip "preparation failed unexpectedly (line $LINENO; see the output above)"' ERR

# sudo only when not root (apt-get); without root and without sudo, missing packages -> skip.
SUDO=()
if [[ $EUID -ne 0 ]]; then
  if command -v sudo >/dev/null && sudo -n true 2>/dev/null; then SUDO=(sudo -n); fi
fi

WHY=""
APT_UPDATED=0
apt_update() {
  [[ $APT_UPDATED == 1 ]] && return 0
  command -v apt-get >/dev/null || return 1
  say "apt-get update"
  "${SUDO[@]}" apt-get update -qq >/dev/null || return 1
  APT_UPDATED=1
}

# --- 1. host packages ------------------------------------------------------------------------
ensure_packages() {
  command -v dpkg-query >/dev/null || { WHY="no dpkg (this recipe needs a Debian host)"; return 1; }
  local missing=() p
  for p in "${APT_PKGS[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
  done
  [[ ${#missing[@]} -eq 0 ]] && return 0
  command -v apt-get >/dev/null || { WHY="no apt-get to install ${missing[*]}"; return 1; }
  if [[ $EUID -ne 0 && ${#SUDO[@]} -eq 0 ]]; then
    WHY="not root and no sudo to install ${missing[*]}"; return 1
  fi
  apt_update || { WHY="apt-get update failed"; return 1; }
  say "apt-get install ${missing[*]}"
  DEBIAN_FRONTEND=noninteractive "${SUDO[@]}" apt-get install -y -qq --no-install-recommends \
    "${missing[@]}" >/dev/null 2>"$CACHE/apt-install.log" \
    || { tail -n 5 "$CACHE/apt-install.log" >&2; WHY="apt-get install ${missing[*]} failed"; return 1; }
}

# --- 2./3. Debian kernel, downloaded (not installed) and pruned to kmin/ ----------------------
KMODS=(fs-9p fs-virtiofs virtio:d00000009v00001AF4 virtio:d00000003v00001AF4 virtio_pci virtio_mmio
       pci:v00001AF4d00001009sv00001AF4sd00000009bc00sc02i00
       pci:v00001AF4d00001003sv00001AF4sd00000003bc07sc80i00
       unix i8042 atkbd overlay vcan can_raw can_bcm can-gw)

find_kernel() {  # prints the vmlinuz in $1/boot whose modules are beside it
  local k
  for k in "$1"/boot/vmlinuz-*; do
    [[ -f $k && -d "$1/lib/modules/${k##*/vmlinuz-}" ]] && { echo "$k"; return 0; }
  done
  return 1
}

build_kmin() {
  local kpkg work deb tmp kver m f rel
  kpkg=$(apt-cache depends linux-image-amd64 2>/dev/null \
         | awk '/Depends: linux-image-[0-9]/ { print $2; exit }') || true
  if [[ -z $kpkg ]]; then
    apt_update || { WHY="apt-get update failed"; return 1; }
    kpkg=$(apt-cache depends linux-image-amd64 2>/dev/null \
           | awk '/Depends: linux-image-[0-9]/ { print $2; exit }') || true
  fi
  [[ -n $kpkg ]] || { WHY="apt knows no linux-image-amd64 kernel"; return 1; }
  work=$(mktemp -d "$CACHE/kbuild.XXXXXX") || return 1
  chmod 755 "$work"  # lets apt's _apt user write the download (no "unsandboxed" warning)
  say "apt-get download $kpkg"
  (cd "$work" && "${SUDO[@]}" apt-get download -qq "$kpkg" >/dev/null 2>"$work/download.log") \
    || { apt_update && (cd "$work" && "${SUDO[@]}" apt-get download -qq "$kpkg" >/dev/null \
                        2>"$work/download.log"); } \
    || { tail -n 5 "$work/download.log" >&2; rm -rf "$work"; WHY="apt-get download $kpkg failed"; return 1; }
  deb=$(ls "$work/${kpkg}"_*.deb) || { rm -rf "$work"; WHY="no .deb after download"; return 1; }
  tmp=$work/x
  mkdir "$tmp"
  dpkg-deb -x "$deb" "$tmp" || { rm -rf "$work"; WHY="dpkg-deb -x $deb failed"; return 1; }
  rm -f "$deb"
  kver=$(ls "$tmp/lib/modules") && [[ -n $kver && -f $tmp/boot/vmlinuz-$kver ]] \
    || { rm -rf "$work"; WHY="$kpkg has no vmlinuz and modules"; return 1; }
  m=$tmp/lib/modules/$kver
  depmod -b "$tmp" "$kver" || { rm -rf "$work"; WHY="depmod failed"; return 1; }
  mkdir -p "$work/kmin/boot" "$work/kmin/lib/modules/$kver"
  cp "$tmp/boot/vmlinuz-$kver" "$tmp/boot/config-$kver" "$work/kmin/boot/"
  for f in "${KMODS[@]}"; do
    modprobe -d "$tmp" -S "$kver" --show-depends "$f" 2>/dev/null | awk '$1 == "insmod" { print $2 }'
  done | sort -u | while read -r f; do
    rel=${f#"$m"/}
    mkdir -p "$work/kmin/lib/modules/$kver/$(dirname "$rel")"
    cp "$f" "$work/kmin/lib/modules/$kver/$rel"
  done
  for f in modules.order modules.builtin modules.builtin.modinfo; do
    [[ -f $m/$f ]] && cp "$m/$f" "$work/kmin/lib/modules/$kver/"
  done
  depmod -b "$work/kmin" "$kver" || { rm -rf "$work"; WHY="depmod of kmin failed"; return 1; }
  [[ -n $(find "$work/kmin/lib/modules/$kver" -name 'vcan.ko*') ]] \
    || { rm -rf "$work"; WHY="$kpkg has no vcan module"; return 1; }
  rm -rf "$CACHE/kmin"
  mv "$work/kmin" "$CACHE/kmin"  # atomic: a half-built tree is never reused
  rm -rf "$work"
}

# --- 4. virtme-ng in its own venv -------------------------------------------------------------
build_venv() {
  local py=$1 v=$CACHE/vng-venv
  rm -rf "$v"  # built in place (a venv cannot be moved) and marked complete at the end
  say "pip install virtme-ng==$VNG_VERSION into $v"
  "$py" -m venv "$v" >/dev/null || { WHY="$py -m venv failed"; return 1; }
  "$v/bin/pip" install -q --disable-pip-version-check "virtme-ng==$VNG_VERSION" >"$CACHE/pip.log" 2>&1 \
    || { tail -n 5 "$CACHE/pip.log" >&2; rm -rf "$v"; WHY="pip install virtme-ng failed"; return 1; }
  echo "$VNG_VERSION" >"$v/.tcf-hil-complete"
}

# --- prepare ------------------------------------------------------------------------------------
mkdir -p "$CACHE" || skip "cannot create the cache directory $CACHE"
if command -v flock >/dev/null; then
  exec 9>"$CACHE/.lock"
  flock -w 1200 9 || skip "another run holds $CACHE/.lock"
fi

# The interpreter the guest command gets: the host's, by absolute path (a venv's bin/python stays
# unresolved so the venv keeps working; a pyenv shim is resolved to the real interpreter).
if [[ -z ${TCF_HIL_PY:-} ]]; then
  HOST_PY=$(command -v python || command -v python3) || skip "no python on PATH"
  TCF_HIL_PY=$("$HOST_PY" -c 'import sys; print(sys.executable)') \
    || skip "$HOST_PY does not run"
fi
[[ $TCF_HIL_PY == /* && -x $TCF_HIL_PY ]] || skip "TCF_HIL_PY=$TCF_HIL_PY is not an absolute executable"

ensure_packages || skip "host packages: ${WHY:-failed}"

if [[ -n ${TCF_HIL_VM_KERNEL:-} ]]; then
  KERNEL=$TCF_HIL_VM_KERNEL
  [[ -f $KERNEL ]] || skip "TCF_HIL_VM_KERNEL=$KERNEL does not exist"
  [[ -d "$(dirname "$KERNEL")/../lib/modules/${KERNEL##*/vmlinuz-}" ]] \
    || skip "no lib/modules/${KERNEL##*/vmlinuz-} beside $KERNEL"
else
  if ! KERNEL=$(find_kernel "$CACHE/kmin"); then
    build_kmin || skip "kernel: ${WHY:-failed}"
    KERNEL=$(find_kernel "$CACHE/kmin") || skip "kernel: no vmlinuz in $CACHE/kmin after pruning"
  fi
fi

if [[ $(cat "$CACHE/vng-venv/.tcf-hil-complete" 2>/dev/null) != "$VNG_VERSION" ]] \
    || ! "$CACHE/vng-venv/bin/vng" --version >/dev/null 2>&1; then
  build_venv "$TCF_HIL_PY" || skip "virtme-ng: ${WHY:-failed}"
fi
# vng shells out to virtme-run by name: put the venv's bin first on PATH.
export PATH=$CACHE/vng-venv/bin:$PATH
command -v qemu-system-x86_64 >/dev/null || skip "qemu-system-x86_64 is missing"

say "prepare: $(took "$T0") (kernel ${KERNEL##*/}, cache $CACHE)"
trap - ERR

# --- boot and run -------------------------------------------------------------------------------
# Empty the output directory, but only one this script made (it holds the .vcan-vm-out mark).
if [[ -d $OUT && ! -f $OUT/.vcan-vm-out && -n $(ls -A "$OUT") ]]; then
  skip "refusing to empty $OUT: not made by this script (no .vcan-vm-out in it)"
fi
if ! { rm -rf "$OUT" && mkdir -p "$OUT" && touch "$OUT/.vcan-vm-out"; }; then
  skip "cannot create the output directory $OUT"
fi
OUT=$(cd "$OUT" && pwd -P)
GUEST_CMD=$(printf '%q ' "$@")
cat >"$OUT/guest.sh" <<EOF
# written by .ci/vcan-vm.sh; runs inside the VM
export VM_OUT=$(printf '%q' "$OUT") TCF_HIL_PY=$(printf '%q' "$TCF_HIL_PY")
export PYTHONDONTWRITEBYTECODE=1 MPLBACKEND=Agg MPLCONFIGDIR=\$VM_OUT/.mpl
echo "\$(uname -r)" >"\$VM_OUT/started"
if ! { modprobe vcan && modprobe can_raw && ip link add dev vcan0 type vcan && ip link set vcan0 up; }; then
  echo "vcan-vm: guest: could not bring up vcan0" >&2
  touch "\$VM_OUT/vcan-failed"
  exit 1
fi
cd $(printf '%q' "$REPO") || exit 1
$GUEST_CMD
rc=\$?
echo "\$rc" >"\$VM_OUT/rc"
exit "\$rc"
EOF

T1=$(now)
say "booting ${KERNEL##*/} (TCG, 2 vCPUs, 1 GiB, limit ${TIMEOUT} s): $GUEST_CMD"
set +e
timeout --kill-after=30 "$TIMEOUT" \
  vng --disable-kvm --force-9p --memory 1G --cpus 2 --user root --rwdir="$OUT" \
      --run "$KERNEL" --exec "bash $(printf '%q' "$OUT/guest.sh")" \
  </dev/null 2>&1 | tee "$OUT/console.log"
vng_rc=${PIPESTATUS[0]}
set -e
say "boot+test: $(took "$T1") (vng rc $vng_rc)"

if [[ ! -f $OUT/started ]]; then
  [[ $vng_rc == 124 || $vng_rc == 137 ]] && skip "the VM did not start within ${TIMEOUT} s"
  skip "the VM did not start (vng rc $vng_rc; log: $OUT/console.log)"
fi
if [[ -f $OUT/vcan-failed ]]; then
  say "FAILED: the guest kernel $(cat "$OUT/started") booted but vcan0 could not be set up"
  exit 1
fi
if [[ ! -f $OUT/rc ]]; then
  if [[ $vng_rc == 124 || $vng_rc == 137 ]]; then
    say "FAILED: the guest command started but did not finish within ${TIMEOUT} s"
  else
    say "FAILED: the guest command started but the VM ended without its exit code (vng rc $vng_rc)"
  fi
  exit 1
fi
rc=$(cat "$OUT/rc")
say "guest command exited $rc; total $(took "$T0")"
exit "$rc"
