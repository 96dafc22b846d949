#!/usr/bin/env bash
# Installs what pointfarm needs beyond the Rust toolchain: a Vulkan driver to render with.
# On machines without a GPU that is Mesa's lavapipe (software Vulkan, Debian package
# mesa-vulkan-drivers; on Debian 12 from bookworm-backports). Does nothing when a lavapipe
# driver is already installed.
#
# The backports source, when one is needed, points at the mirror the machine's own Debian
# sources use for bookworm; with none found, bookworm's own Mesa is installed. Sourcing this
# file defines the functions without running anything (`source deploy/setup.sh;
# debian_mirror /etc/apt`), which is how the mirror detection is tested.
set -euo pipefail

# Prints one line per enabled apt entry and suite under the apt directory $1 (sources.list,
# sources.list.d/*.list one-line entries and sources.list.d/*.sources deb822 paragraphs):
#   FORMAT TYPES URI SUITE SIGNED_BY
# FORMAT is "list" or "sources"; TYPES is comma-separated (deb,deb-src); URI is the entry's
# first; SIGNED_BY is the key file or "-". Files apt ignores (other endings) are skipped.
apt_entries() {
    local dir=$1 file
    local lists=() deb822=()
    [ -f "$dir/sources.list" ] && lists+=("$dir/sources.list")
    for file in "$dir"/sources.list.d/*.list; do
        [ -f "$file" ] && lists+=("$file")
    done
    for file in "$dir"/sources.list.d/*.sources; do
        [ -f "$file" ] && deb822+=("$file")
    done
    if [ ${#lists[@]} -gt 0 ]; then
        # deb [opt=value ...] URI SUITE [COMPONENT...]
        awk '
            { sub(/#.*/, "") }
            $1 != "deb" && $1 != "deb-src" { next }
            {
                type = $1; signed = "-"; i = 2
                if ($2 ~ /^\[/) {
                    while (i <= NF) {
                        opt = $i; gsub(/[][]/, "", opt)
                        if (opt ~ /^signed-by=/) { signed = substr(opt, 11) }
                        if ($i ~ /\]$/) { i++; break }
                        i++
                    }
                }
                if (i + 1 <= NF) { print "list", type, $i, $(i + 1), signed }
            }' "${lists[@]}"
    fi
    if [ ${#deb822[@]} -gt 0 ]; then
        # Paragraphs of "Field: value" lines, separated by blank lines; continuation lines
        # (an embedded key) start with white space and are skipped.
        awk '
            function flush(   n, s, suites) {
                if (types != "" && uri != "" && enabled != "no") {
                    n = split(suite_list, suites, " ")
                    for (s = 1; s <= n; s++) { print "sources", types, uri, suites[s], signed }
                }
                types = ""; uri = ""; suite_list = ""; signed = "-"; enabled = ""
            }
            BEGIN { flush() }
            FNR == 1 && NR != 1 { flush() }
            /^[ \t]*#/ { next }
            /^[ \t]*$/ { flush(); next }
            /^[ \t]/ { next }
            {
                field = tolower($0); sub(/:.*/, "", field)
                value = $0; sub(/^[^:]*:[ \t]*/, "", value); sub(/[ \t]+$/, "", value)
                if (field == "types") { types = value; gsub(/[ \t]+/, ",", types) }
                else if (field == "uris") { split(value, uris, /[ \t]+/); uri = uris[1] }
                else if (field == "suites") { suite_list = value }
                else if (field == "enabled") { enabled = tolower(value) }
                else if (field == "signed-by" && value ~ /^\//) { signed = value }
            }
            END { flush() }' "${deb822[@]}"
    fi
}

# Prints "FORMAT URI SIGNED_BY" for the main Debian archive's bookworm entry under the apt
# directory $1 (a binary "deb" entry for the suite "bookworm" itself, not the security
# archive, not a CD), or nothing when there is none.
debian_mirror() {
    apt_entries "$1" | awk '
        !found && $4 == "bookworm" && ("," $2 ",") ~ /,deb,/ && $3 !~ /debian-security/ && $3 !~ /^cdrom:/ {
            print $1, $3, $5; found = 1
        }'
}

# Succeeds when an enabled entry under the apt directory $1 already carries the suite $2.
has_suite() {
    apt_entries "$1" | awk -v suite="$2" '$4 == suite { found = 1 } END { exit !found }'
}

# Writes the bookworm-backports source for the mirror "FORMAT URI SIGNED_BY" ($1) in the
# style of the entry it came from, to the apt directory $2, with the command $3 ("" or sudo),
# and prints the file's path.
write_backports_source() {
    local format uri signed file
    read -r format uri signed <<<"$1"
    if [ "$format" = sources ]; then
        file="$2/sources.list.d/pointfarm-bookworm-backports.sources"
        {
            echo "Types: deb"
            echo "URIs: $uri"
            echo "Suites: bookworm-backports"
            echo "Components: main"
            if [ "$signed" != - ]; then echo "Signed-By: $signed"; fi
        } | $3 tee "$file" >/dev/null
    else
        local options=""
        file="$2/sources.list.d/pointfarm-bookworm-backports.list"
        if [ "$signed" != - ]; then options="[signed-by=$signed] "; fi
        echo "deb ${options}$uri bookworm-backports main" | $3 tee "$file" >/dev/null
    fi
    echo "$file"
}

main() {
    if compgen -G "/usr/share/vulkan/icd.d/lvp_icd*.json" >/dev/null; then
        exit 0
    fi

    echo "pointfarm setup: installing Mesa's lavapipe (mesa-vulkan-drivers)" >&2
    if ! command -v apt-get >/dev/null; then
        echo "pointfarm setup: no apt-get here; install Mesa's Vulkan drivers (lavapipe) with your package manager" >&2
        exit 1
    fi
    local sudo=""
    if [ "$(id -u)" -ne 0 ]; then
        sudo="sudo"
    fi
    export DEBIAN_FRONTEND=noninteractive
    local packages=(mesa-vulkan-drivers libvulkan1)
    local installed="" apt_dir=/etc/apt codename mirror uri written=""
    # Debian 12 ships Mesa 22.3, whose lavapipe runs pointfarm's passes slower than the Mesa 25
    # of Debian 13, which bookworm-backports carries too (docs/perf/mesa-versions.md): on
    # Debian 12 lavapipe comes from there, unless POINTFARM_MESA=stock. Any failure falls back
    # to bookworm's own.
    codename=$(. /etc/os-release 2>/dev/null && echo "${VERSION_CODENAME:-}") || codename=""
    if [ "$codename" = bookworm ] && [ "${POINTFARM_MESA:-backports}" != stock ]; then
        local backports=yes
        if ! has_suite "$apt_dir" bookworm-backports; then
            mirror=$(debian_mirror "$apt_dir")
            if [ -n "$mirror" ]; then
                read -r _ uri _ <<<"$mirror"
                echo "pointfarm setup: adding bookworm-backports from the machine's bookworm mirror, $uri" >&2
                written=$(write_backports_source "$mirror" "$apt_dir" "$sudo")
            else
                echo "pointfarm setup: no Debian mirror for bookworm in $apt_dir's sources; installing bookworm's own Mesa (22.3) instead of bookworm-backports'" >&2
                backports=no
            fi
        fi
        if [ "$backports" = yes ]; then
            if $sudo apt-get update -qq &&
                $sudo apt-get install -y -qq --no-install-recommends -t bookworm-backports "${packages[@]}" >/dev/null; then
                installed=backports
            else
                echo "pointfarm setup: lavapipe from bookworm-backports failed; installing bookworm's" >&2
                # A source that broke the update must not break the fallback's update too.
                if [ -n "$written" ]; then $sudo rm -f "$written"; fi
            fi
        fi
    fi
    if [ -z "$installed" ]; then
        $sudo apt-get update -qq
        $sudo apt-get install -y -qq --no-install-recommends "${packages[@]}" >/dev/null
    fi
    compgen -G "/usr/share/vulkan/icd.d/lvp_icd*.json" >/dev/null || {
        echo "pointfarm setup: mesa-vulkan-drivers installed but no lavapipe driver found" >&2
        exit 1
    }
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
    main "$@"
fi
