"""Headless Chromium for the page tests: Debian's ``chromium`` and ``chromium-driver`` (installed with apt-get when
missing and possible), driven by Selenium; WebGL through SwiftShader (no GPU, no display)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

PACKAGES = ("chromium", "chromium-driver")


def find_chromium(install: bool = True) -> tuple[str, str] | str:
    """``(chromium, chromedriver)`` paths, or the reason they cannot be had (installs them as root when missing)."""

    def found() -> tuple[str, str] | None:
        browser = shutil.which("chromium") or shutil.which("chromium-browser")
        driver = shutil.which("chromedriver") or next(
            (p for p in ("/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver") if Path(p).is_file()), None
        )
        return (browser, driver) if browser and driver else None

    paths = found()
    if paths is None and install and shutil.which("apt-get") and os.geteuid() == 0:
        argv = ["apt-get", "install", "-y", "-qq", *PACKAGES]
        for argvs in ([argv], [["apt-get", "update", "-qq"], argv]):
            for a in argvs:
                subprocess.run(a, capture_output=True, timeout=900, check=False)
            paths = found()
            if paths:
                break
    if paths is None:
        return "chromium and chromium-driver are not installed and could not be installed with apt-get"
    return paths


def start_chromium(browser: str, driver: str, downloads: Path, width: int = 1280, height: int = 1500) -> Any:
    """A headless Chromium session (Selenium WebDriver) saving downloads into ``downloads``."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        f"--window-size={width},{height}",
        "--use-angle=swiftshader",  # WebGL on the CPU
        "--enable-unsafe-swiftshader",
        "--ignore-gpu-blocklist",
        "--no-first-run",
        "--disable-extensions",
    ):
        options.add_argument(arg)
    options.add_experimental_option(
        "prefs", {"download.default_directory": str(downloads), "download.prompt_for_download": False}
    )
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(executable_path=driver), options=options)


def open_page_with_file(driver: Any, base_url: str, path: Path, key: str = "key-a") -> None:
    """The page at ``base_url`` with the API key saved and ``path`` chosen in its file picker (shown by its name)."""
    from selenium.webdriver.common.by import By

    from tests.service.procs import wait_until

    driver.get(base_url + "/")
    driver.find_element(By.ID, "api-key").send_keys(key)
    driver.find_element(By.ID, "key-save").click()
    file_input = driver.find_element(By.ID, "file-input")
    driver.execute_script("arguments[0].hidden = false", file_input)
    file_input.send_keys(str(path))
    name = path.name.split(".")[0]
    wait_until(lambda: name in driver.find_element(By.ID, "picked").text, 10, "the file to be picked")
