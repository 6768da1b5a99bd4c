// The view the user asked for (its #/job/ID) is in the URL's fragment, which no request carries: the form
// posts to a URL with that fragment, and the browser keeps it across the redirect to the page (RFC 9110
// 10.2.2), so the user lands on the job they opened, not on the list.
document.getElementById("login-form").action = "/ui/login" + window.location.hash;
